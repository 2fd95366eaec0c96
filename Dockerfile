# One image for every service of docker-compose.yml: the tupa command with everything installed
# (torch==2.13.0 CPU and the package; the optional ns-3 and Ray extras are left out), run as the
# unprivileged user tupa (uid 10001). No secret is baked in: TUPA_API_TOKEN comes from the
# environment at run time (docker-compose.yml), never from a build argument (build arguments show
# in `docker history`: an index URL with a password does not belong in TORCH_INDEX_URL; fetch the
# wheels outside with scripts/wheelhouse.sh and build with OFFLINE=1 instead).
#
#   docker build -t tupa .                                   # python:3.11-slim, PyPI + PyTorch's CPU index
#   scripts/build_image.sh                                   # offline: Debian base + local wheels
#   docker build --build-arg BASE=tupa-base:bookworm --build-arg OFFLINE=1 -t tupa .
#
# BASE: any Debian-like image with python3.11 and its venv module: python:3.11-slim (default), or
# the one scripts/offline_base.sh builds from Debian's packages where no image registry is
# reachable. OFFLINE=1 installs only from build/wheels (scripts/wheelhouse.sh fills it), with no
# network. Stages: the dependencies (cached until their list or the wheels change), the package
# (rebuilt on a code change: seconds), the final image (the two copied in, no build tools).
ARG BASE=python:3.11-slim

# The dependency list from pyproject.toml, and the wheels when there are any: the next stage's
# cache key is their content, so an edit elsewhere in pyproject.toml reinstalls nothing.
FROM ${BASE} AS requirements
# build/wheel[s]: a pattern, so that a context without build/wheels still builds.
COPY pyproject.toml build/wheel[s] /wheels/
# With the wheels comes their constraints.txt (the versions make test ran): they are kept to.
RUN python3.11 -c "import tomllib; p = tomllib.load(open('/wheels/pyproject.toml', 'rb')); \
print('\n'.join(['torch==2.13.0', *p['project']['dependencies'], *p['build-system']['requires']]))" \
        > /wheels/requirements.txt \
    && if [ -s /wheels/constraints.txt ]; then echo '-c /wheels/constraints.txt' >> /wheels/requirements.txt; fi \
    && rm /wheels/pyproject.toml

FROM ${BASE} AS deps
ARG OFFLINE=0
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
COPY --from=requirements /wheels/ /wheels/
# torch first, from PyTorch's CPU index (online) or the wheels (offline); then the rest. What
# only building against torch or testing torch needs is dropped (headers, CMake files, its C++
# test programs): about 140 MB.
RUN set -eu; \
    if [ "$OFFLINE" = 1 ]; then torch_from="--no-index"; rest_from="--no-index"; \
    else torch_from="--index-url $TORCH_INDEX_URL"; rest_from=""; fi; \
    python3.11 -m venv /opt/tupa; \
    /opt/tupa/bin/pip install --quiet --find-links /wheels $torch_from 'torch==2.13.0'; \
    /opt/tupa/bin/pip install --quiet --find-links /wheels $rest_from -r /wheels/requirements.txt; \
    site=/opt/tupa/lib/python3.11/site-packages; \
    rm -rf "$site/torch/include" "$site/torch/share/cmake" "$site/torch/test"; \
    find "$site/torch/bin" -type f ! -name torch_shm_manager -delete

# The package itself, built into its own directory so that the final image copies only it.
FROM deps AS code
COPY pyproject.toml README.md /src/
COPY sim /src/sim
COPY policies /src/policies
COPY service /src/service
COPY api /src/api
COPY closed_loop /src/closed_loop
COPY sitl_mock /src/sitl_mock
RUN /opt/tupa/bin/pip install --quiet --no-index --no-deps --no-build-isolation \
        --target /pkg/site /src \
    && mkdir /pkg/bin && mv /pkg/site/bin/tupa /pkg/bin/tupa && rmdir /pkg/site/bin

FROM ${BASE}
RUN groupadd --system --gid 10001 tupa \
    && useradd --system --uid 10001 --gid tupa --create-home --home-dir /home/tupa \
        --shell /usr/sbin/nologin tupa \
    && install -d -o tupa -g tupa /state /runs
COPY --from=deps /opt/tupa /opt/tupa
COPY --from=code /pkg/site/ /opt/tupa/lib/python3.11/site-packages/
COPY --from=code /pkg/bin/tupa /opt/tupa/bin/tupa
ENV PATH=/opt/tupa/bin:$PATH PYTHONUNBUFFERED=1 PYTHONDONTWRITEBYTECODE=1
USER tupa
WORKDIR /home/tupa
ENTRYPOINT ["tupa"]
CMD ["--help"]
