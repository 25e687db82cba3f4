"""The building blocks every srl process shares, in floors from the ground up (docs/architecture.md):

    system/     OS-level, no srl concept: die with the parent, clocks, atomic files, the JIT build
    math/       numbers and arrays: dynamics, features, critics, the actor, Algorithm 1, robot models
    contracts/  what crosses a process boundary: keys, wire messages, run summaries, the ROS 2 wire
    config/     settings (the one srl.toml), their command-line flags, Settings -> math objects
    net/        the Zenoh transport and its security
    process/    a process's life: signals, the session, the summary, the exit

A module imports ``common`` only from its own floor or the floors below, never ``services`` or ``tools``;
``common.net.transport`` is the only module that imports zenoh, and none imports ROS
(tests/test_architecture.py and tests/test_purity.py check both).
"""

from common.system.blas import pin_openblas_kernel

pin_openblas_kernel()  # before any module of common loads numpy: the same bits on every x86_64 CPU
