"""tofloc: robot localization in a known map from distributed multizone Time-of-Flight sensors.

The shared core: frames (:mod:`tofloc.frames`), sensor geometry (:mod:`tofloc.rig`),
log format v1 (:mod:`tofloc.logs`), maps (:mod:`tofloc.maps`), the simulator
(:mod:`tofloc.simulation`), k-NN kinematics (:mod:`tofloc.kinematics`) and the plug-in
registry (:mod:`tofloc.registry`). Estimators, sensor models and the evaluation code
live in the top-level packages ``estimators``, ``sensor_models`` and ``evaluation``.
"""

__version__ = "0.1.0"

# before anything imports Open3D: the newer TBB runtime serves Open3D and numba alike
from tofloc.tbb_runtime import preload as _preload_tbb

_preload_tbb()
