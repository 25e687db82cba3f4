"""Tools above the services: the srl command (commands/), the launcher (launch/), recordings and the
live view (recording/), benchmarks (bench/), the experiment (experiment/), the generated docs (docs/).

Importing this package (every ``srl`` command does, first) gives the process one OpenBLAS thread
unless the user set ``OPENBLAS_NUM_THREADS``: it must be set before numpy, scipy or casadi load
OpenBLAS, which reads it once. srl's matrices are small (a robot's Q-critic design is M x 15), and
an OpenBLAS worker spins on a core after each call: ``srl bench actor``'s SLSQP solves kept the
second of two cores busy (2 min 49 s of CPU in 1 min 27 s; with one thread 1 min 30 s in 1 min 31 s,
every figure of ``srl experiment paper`` bit for bit the same)."""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
