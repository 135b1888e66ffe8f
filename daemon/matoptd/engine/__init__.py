"""The engine: the only code of matopt that imports mitsuba and drjit.

Every function here runs on the scheduler's worker thread, one call at a time: Mitsuba 3.9
breaks when AD work runs in several threads of one process, and ``mi.set_variant`` is global.
"""
