"""detaug_gym: obstacle-avoidance benchmarks for manipulation policies and the DetAug method.

``import detaug_gym`` registers the gymnasium ids (``SafeLibero-Spatial-L2-v0``, ...) without loading
MuJoCo; ``gym.make("detaug_gym:SafeLibero-Spatial-L2-v0")`` works as well.
"""

from detaug_gym import envs  # noqa: F401  (registers the env ids)

__version__ = "0.1.0"
