# One image for every srl service: `srl router`, `srl actor`, `srl critic`, `srl plant-sim`, ...
#
# Two stages: `build` installs the project and its dependencies into a virtual environment,
# the final stage copies only that environment onto a clean BASE (no wheels, no pip cache, no
# build tree in any layer of the image). The build stage takes the wheels from one of two places:
#
# * dist/wheels (offline): `docker/build-wheels` put the project's wheel and every dependency
#   there on the host; then `pip install --no-index` and the build needs no network (CI builds
#   with `--network none` and proves it):
#       docker/build-wheels && docker build --network none -t srl:latest .
# * otherwise PyPI: the project's wheel is built from the source here and its dependencies are
#   downloaded (binary wheels): what a fresh clone gets from `docker compose up`.
#
# BASE must provide python3 3.11 with the venv module. The default is the standard slim image;
# where no registry is reachable, build one from Debian's packages (docker/build-base: mmdebstrap
# + docker import; .ci/compose-test does):
#
#   docker build --build-arg BASE=srl-base:bookworm -t srl:latest .
#
# arm64 (a TurtleBot3's Raspberry Pi 4, docs/turtlebot.md#the-actor-on-the-robots-raspberry-pi):
# python:3.11-slim is a multi-architecture image and every dependency has an aarch64 wheel on
# PyPI, so the same Dockerfile builds for linux/arm64 (on an x86_64 host through buildx and
# qemu-user; .ci/aarch64-test runs srl under that emulation):
#       docker buildx build --platform linux/arm64 -t srl:arm64 --load .
# dist/wheels are used only when they were built for the architecture being built (docker/build-wheels
# downloads its host's), else the build goes to PyPI as without them.
#
# JIT: the actor can compile its optimal-control problem with a C compiler. Measured on 2 vCPUs
# (casadi 3.8.2, fatrop): median solve 0.40-0.59 ms compiled vs 0.46-0.77 ms not (N = 12), and
# 0.6-1.0 ms vs 0.7-1.5 ms (N = 30); compiling costs 0.9-4.8 s at every actor start and gcc
# adds 200 MB (a bookworm rootfs with python3: 219 MB; with gcc and libc6-dev: 421 MB). Both are
# far below the 100 ms sampling period, so the image ships no compiler and sets
# SRL_ACTOR__JIT=false. With a BASE that has gcc, build with --build-arg JIT=true (or
# `docker run -e SRL_ACTOR__JIT=true`).
ARG BASE=python:3.11-slim

FROM ${BASE} AS build
ENV PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_NO_CACHE_DIR=1 PYTHONDONTWRITEBYTECODE=1
# the build context is the source and, if present, dist/wheels (.dockerignore)
COPY . /src
# A virtual environment, not the system site-packages (Debian's python3 refuses pip installs
# there, PEP 668). Then pip and the dependencies' own test suites (numpy, scipy, matplotlib, ...:
# ~57 MB) are removed: the image never installs anything and never runs them.
RUN python3 -m venv /opt/srl \
 && if ls /src/dist/wheels/srl-*.whl /src/dist/wheels/*_"$(uname -m)".whl >/dev/null 2>&1; then \
      echo "srl image: installing from dist/wheels (offline, --no-index)"; \
      /opt/srl/bin/python -m pip install --no-index --find-links /src/dist/wheels 'srl[physics]'; \
    else \
      echo "srl image: no dist/wheels for $(uname -m): building srl and fetching its dependencies from PyPI"; \
      /opt/srl/bin/python -m pip install --prefer-binary '/src[physics]' \
      || { echo "srl image: the install from PyPI failed; without network, run docker/build-wheels first (docs/getting-started.md)" >&2; exit 1; }; \
    fi \
 && /opt/srl/bin/python -m pip uninstall --yes --quiet pip \
 && find /opt/srl/lib -depth -type d -name tests -path '*/site-packages/*/tests' -exec rm -rf {} + \
 && /opt/srl/bin/srl --help >/dev/null

FROM ${BASE}
ARG JIT=false
ENV PATH=/opt/srl/bin:${PATH} \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    SRL_ACTOR__JIT=${JIT}
COPY --from=build /opt/srl /opt/srl
# ~/.local/state/srl is the critic's checkpoint directory, owned by srl so that the named volume
# docker-compose.yml mounts there is too. The last line proves the entry point starts.
RUN useradd --system --create-home --home-dir /home/srl --uid 10001 --user-group --shell /usr/sbin/nologin srl \
 && install -d -o srl -g srl /home/srl/.local /home/srl/.local/state /home/srl/.local/state/srl \
 && srl --help >/dev/null

USER srl
WORKDIR /home/srl
ENTRYPOINT ["srl"]
CMD ["--help"]
