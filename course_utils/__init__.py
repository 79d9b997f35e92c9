"""course_utils: the small library behind the policy-gradient course.

Modules, by concept: ``config`` (presets, validation), ``rewards`` (the rule checker),
``losses`` (estimators and GRPO's loss), ``rollout`` (sampling and scoring tokens), ``models``,
``data``, ``train`` (the GRPO loop and the command line), ``checkpoint``, ``plots``,
``toy`` (small problems with exact answers, for the lessons) and ``exercises`` (the checkers).
"""

# Where the course is published: the Colab badges and set-up cells are generated from this one
# line (notebooks/build.py), and a test checks that every notebook agrees with it.
GITHUB_REPO = "policy-gradients-course/policy-gradients-for-llms"

__version__ = "0.1.0"
