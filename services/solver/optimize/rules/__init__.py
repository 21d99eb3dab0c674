"""The rules :func:`services.solver.optimize.resolve.resolve` applies, one module each: the rule,
its constants, the reason a user reads in ``plan.json`` and the benchmark it rests on, side by
side. Pure: the scene enters only through :class:`~.inputs.Measures`."""
