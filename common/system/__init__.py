"""OS-level helpers with no srl concept: die with the parent (lifeline), absolute-time ticks
(clock), atomic and private files (checkpoint), the JIT build of CasADi functions (jit), free
loopback ports below the ephemeral range (ports).

The ground floor: imports nothing of ``common``.
"""
