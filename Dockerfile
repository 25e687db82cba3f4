# One image for every srl service: `srl router`, `srl actor`, `srl critic`, `srl plant-sim`, ...
#
# The project and all its dependencies are installed from wheels built on the host, so the build
# and the containers need no network:
#
#   docker/build-wheels              # dist/wheels: srl + binary wheels for CPython 3.11, glibc Linux
#   docker build --network none -t srl:latest .        # or: docker compose build
#
# BASE must provide python3 3.11 (the wheels' interpreter) with the venv module. The default is
# the standard slim image; where no registry is reachable, build one from Debian's packages
# (docker/build-base: mmdebstrap + docker import; .ci/compose-test does):
#
#   docker build --build-arg BASE=srl-base:bookworm -t srl:latest .
#
# JIT: the actor can compile its optimal-control problem with a C compiler. Measured on 2 vCPUs
# (casadi 3.8.2, fatrop): median solve 0.40-0.59 ms compiled vs 0.46-0.77 ms not (N = 12), and
# 0.6-1.0 ms vs 0.7-1.5 ms (N = 30); compiling costs 0.9-4.8 s at every actor start and gcc
# adds 200 MB (a bookworm rootfs with python3: 219 MB; with gcc and libc6-dev: 421 MB). Both are far below the 100 ms sampling period, so the image
# ships no compiler and sets SRL_ACTOR__JIT=false. With a BASE that has gcc, build with
# --build-arg JIT=true (or `docker run -e SRL_ACTOR__JIT=true`).
ARG BASE=python:3.11-slim
FROM ${BASE}

ARG JIT=false
ENV PATH=/opt/srl/bin:${PATH} \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    SRL_ACTOR__JIT=${JIT}

COPY dist/wheels/ /tmp/wheels/
# A virtual environment, not the system site-packages (Debian's python3 refuses pip installs
# there, PEP 668). --no-index: every wheel comes from the build context, never the network.
# ~/.local/state/srl is the critic's checkpoint directory, owned by srl so that the named volume
# docker-compose.yml mounts there is too. The last line proves the entry point starts.
RUN python3 -m venv /opt/srl \
 && /opt/srl/bin/python -m pip install --no-index --no-cache-dir --find-links /tmp/wheels srl \
 && rm -rf /tmp/wheels \
 && useradd --system --create-home --home-dir /home/srl --uid 10001 --user-group --shell /usr/sbin/nologin srl \
 && install -d -o srl -g srl /home/srl/.local /home/srl/.local/state /home/srl/.local/state/srl \
 && srl --help >/dev/null

USER srl
WORKDIR /home/srl
ENTRYPOINT ["srl"]
CMD ["--help"]
