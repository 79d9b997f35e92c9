"""Settings for everything pytest runs here, the notebooks under nbmake included (their kernels
inherit this environment): smoke mode, and no model hub."""
import os

os.environ.setdefault("COURSE_SMOKE", "1")
os.environ.setdefault("HF_HUB_OFFLINE", "1")
