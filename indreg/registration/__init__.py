"""The registration set-up: ``indreg.register`` (``api``), the run it shares with the app (``run``: set-up, loop,
result) and the registries it builds from: the deformation models (``models``), the solvers (``solver_registry``)
and the in-the-fit corrections (``corrections``); the option table they declare their options in is
``indreg.options``. Each module is also importable by its former name (``indreg.registration.run``, ``indreg.registration.models``, ...)."""
