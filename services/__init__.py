"""The domain core of the NDRF inverse-rendering service.

``solver``      the method: scenes, sampling, the neural fields, the estimators and the loop of
                Sec. 5 (imports only Mitsuba, Dr.Jit, torch, numpy and ``schemas``)
``uploads``     checks of untrusted scenes, meshes and images, and the staging of uploads
``store``       the artifact store (the source of truth): a folder or an S3 bucket
``queue``       the job queue and the per-job event streams (Redis, or in-process)
``jobs``        the job service, the one owner of a job's state, the sandboxed execution of an
                attempt and the writer of its reports
``limits``, ``settings``, ``runtime``   caps, the one ``Settings``, and the wiring of a process

Nothing here has import-time side effects: the Mitsuba variant is chosen by
:func:`services.solver.backend.use_mitsuba`, called by whoever first needs a scene.
"""
