"""The engine: the only code of matopt that imports mitsuba and drjit.

It runs in worker processes only (``matoptd.workers.serve``), one call at a time: Mitsuba 3.9
breaks when AD work runs in several threads of one process, and ``mi.set_variant`` is global.
``service.MitsubaEngine`` implements ``matoptd.engine_api.Engine``, the daemon's one way in;
``startup`` prepares a worker before its first call.
"""
