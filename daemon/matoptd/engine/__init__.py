"""The engine: the only code of matopt that imports mitsuba and drjit.

It runs in worker processes only (``matoptd.workers.serve``), one call at a time: Mitsuba 3.9
breaks when AD work runs in several threads of one process, and ``mi.set_variant`` is global.
``service.MitsubaEngine`` implements ``matoptd.engine_api.Engine``, the daemon's one way in;
``startup`` prepares a worker before its first call.

A job's optimization is ``optimize.Optimization``: one loop over plain data, a record per
variable (``records.ParamRecord``), the renders (``renders``), the guards (``guards``) and the
maps from Adam's variable to the scene's value (``maps``), which the named choices in
``choices/`` contribute; a choice sees a ``context.Context`` and its own records, never the
loop. A checkpoint is that state by name (``checkpoint``). At the end, ``jacobian`` and
``uncertainty`` give each kept value a standard error (the model: ``covariance``), and
``diagnosis`` reads the history.

Adding a loss: write its Dr.Jit function in ``losses.py`` and declare it in ``LOSSES`` there
(renders per iteration, the window its estimates are averaged over, a title, and how the
standard errors treat it); give it a value ``LOSS_<NAME>`` in the API's ``Loss`` enum
(proto/matopt/v1/matopt.proto, with a comment). Nothing else names losses:
tests/test_registries.py checks the two lists agree.

Adding a choice: a module in ``choices/`` with a ``Choice`` subclass (its ``select``, ``setup``
and the hooks it needs, returning what they change), placed in ``choices.REGISTRY`` where its
hooks must run; declare how it meets others (``after``, ``yields_to``, ``excludes``). A
choice a job may turn off is also named, with a line on what it does, in
``settings.CHOICES``. tests/test_loop.py shows the hook contract with fake choices.
"""
