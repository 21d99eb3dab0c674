"""The solver: scenes, Monte Carlo sampling, the neural fields, the estimators and the
inverse-rendering loop of the paper (Sec. 4-6).

It imports only Mitsuba, Dr.Jit, torch, numpy and :mod:`schemas` (an import-linter contract in
``pyproject.toml`` checks it): nothing here knows about jobs, queues, stores or HTTP. A run reports
through the :class:`services.solver.optimize.report.RunReporter` its host gives it.

Sub-packages, in the order one job's data flows through them:

``scene``       load a scene (built-in, XML file, dict), its optimizable parameters, the probe of
                what it can produce and `choose_effects`
``sampling``    Monte Carlo sampling on Mitsuba/Dr.Jit: residual points, incident directions (MIS),
                delta chains, camera rays and film splatting
``fields``      the two neural fields (PyTorch): ``L_phi`` and ``dL_theta``
``estimators``  residuals of Eq. 5/6 (training), the gradient methods (Eq. 3, 10, 11) and their
                registry, the path-traced candidate render
``optimize``    the alternating inverse-rendering loop of Sec. 5

Nothing here has import-time side effects: the Mitsuba variant is chosen by
:func:`services.solver.backend.use_mitsuba`, called by whoever first needs a scene.
"""
