"""A process's life: signals, the session, the summary and the exit (runtime), and per-robot
counters of a process that serves many (counts).

The top floor of ``common``: may import any floor below; never ``services`` or ``tools``.
"""
