"""course_utils: the small library behind the policy-gradient course."""
