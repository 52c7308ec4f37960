"""Example kdtrace plug-ins (see kdtrace's README, "Validate your own method").

``brute_force.make(scene)``
    every ray against every triangle in float64 NumPy: slow, exact, small scenes only;
``bilateral.make()``
    a cross-bilateral filter guided by albedo and normal.

Neither imports kdtrace: a plug-in needs only the two interfaces of
``kdtrace.plugins`` (``Accelerator``, ``Denoiser``).
"""
