"""Shared fixtures: building a LIBERO scene costs seconds, so env fixtures are module-scoped."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
