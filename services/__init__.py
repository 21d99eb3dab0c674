"""The domain core of the NDRF inverse-rendering service.

Sub-packages, in the order one job's data flows through them:

``scene``       load a scene (built-in, sandboxed XML + files, dict), list and select its parameters
``sampling``    Monte Carlo sampling on Mitsuba/Dr.Jit: residual points, incident directions (MIS),
                delta chains, camera rays and film splatting
``fields``      the two neural fields (PyTorch): ``L_phi`` and ``dL_theta``
``estimators``  residuals of Eq. 5/6 (training) and the five gradient methods (Eq. 3, 10, 11)
``optimize``    the alternating inverse-rendering loop of Sec. 5
``store``       the artifact store (job folders, atomic writes, images)
``queue``       the Redis queue and per-job event streams

Nothing here has import-time side effects: the Mitsuba variant is chosen by
:func:`services.backend.use_mitsuba`, called by whoever first needs a scene.
"""
