# deepcontact's images, by role (docs/deployment.md):
#   docker build --target server -t deepcontact-server .   # serves models/: no TensorFlow, no Box2D, no compilers
#   docker build --target client -t deepcontact-client .   # simulates against a server: the patched Box2D, no TensorFlow
# The build stage compiles what they need (deepcontact's C kernels, the patched pybox2d wheel);
# the runtime stages install the wheels, pinned by requirements.lock, and nothing else.
ARG PYTHON_IMAGE=python:3.11-slim-bookworm
# The runtime stages' base: the same by default; any Python 3.11 with venv and CA certificates.
ARG RUNTIME_IMAGE=${PYTHON_IMAGE}

FROM ${PYTHON_IMAGE} AS build
# A proxy's certificate authority, where the network re-signs TLS (docker/extra-ca/README.md).
COPY docker/extra-ca/ /usr/local/share/ca-certificates/
RUN update-ca-certificates
ENV PIP_CERT=/etc/ssl/certs/ca-certificates.crt
RUN apt-get update \
    && apt-get install -y --no-install-recommends build-essential patch \
    && rm -rf /var/lib/apt/lists/*
# A virtual environment of its own: Debian's Python refuses pip into the system (PEP 668).
RUN python3.11 -m venv /opt/build
ENV PATH=/opt/build/bin:$PATH
WORKDIR /src
COPY requirements.lock pyproject.toml setup.py README.md ./
RUN pip install --no-cache-dir --constraint requirements.lock setuptools wheel swig numpy
COPY box2d/ box2d/
# The patched Box2D first: it changes only with box2d/, so code edits do not rebuild it.
RUN PYTHON=/opt/build/bin/python bash box2d/build.sh /wheels/box2d
COPY deepcontact/ deepcontact/
COPY simclient/ simclient/
COPY server/ server/
COPY training/ training/
COPY bench/ bench/
COPY commands/ commands/
COPY lab/ lab/
COPY proto/ proto/
RUN pip wheel --no-cache-dir --no-deps --no-build-isolation -w /wheels/deepcontact .

FROM ${RUNTIME_IMAGE} AS runtime
COPY docker/extra-ca/ /usr/local/share/ca-certificates/
RUN update-ca-certificates
ENV PIP_CERT=/etc/ssl/certs/ca-certificates.crt
ENV PATH=/opt/deepcontact/bin:$PATH PYTHONUNBUFFERED=1
WORKDIR /app

FROM runtime AS server
COPY requirements.lock /tmp/requirements.lock
COPY --from=build /wheels/deepcontact/ /tmp/wheels/
# One layer: the environment, what it serves with, and pip taken out again (nothing installs later).
RUN python3.11 -m venv /opt/deepcontact \
    && pip install --no-cache-dir --constraint /tmp/requirements.lock /tmp/wheels/*.whl \
    && pip uninstall --yes pip setuptools \
    && rm -rf /tmp/wheels /tmp/requirements.lock
COPY models/ models/
EXPOSE 50051
HEALTHCHECK --interval=5s --timeout=5s --retries=12 CMD ["deepcontact", "health", "--server", "127.0.0.1:50051"]
ENTRYPOINT ["deepcontact"]
# Inside a container network: plaintext there only (docs/server.md, Exposure).
CMD ["serve", "--models", "models/", "--bind", "0.0.0.0:50051", "--insecure"]

FROM runtime AS client
COPY requirements.lock /tmp/requirements.lock
COPY --from=build /wheels/ /tmp/wheels/
# [bench]: the figures and latency histograms of bench iterations and bench load.
RUN python3.11 -m venv /opt/deepcontact \
    && pip install --no-cache-dir --constraint /tmp/requirements.lock \
        "$(ls /tmp/wheels/deepcontact/*.whl)[bench]" /tmp/wheels/box2d/*.whl \
    && pip uninstall --yes pip setuptools \
    && rm -rf /tmp/wheels /tmp/requirements.lock
COPY examples/ examples/
ENTRYPOINT ["deepcontact"]
CMD ["--help"]

# docker compose --profile scale: the client with Ray, for the Ray head, workers and the sweep (docs/scale.md).
FROM runtime AS cluster
COPY requirements.lock /tmp/requirements.lock
COPY --from=build /wheels/ /tmp/wheels/
RUN python3.11 -m venv /opt/deepcontact \
    && pip install --no-cache-dir --constraint /tmp/requirements.lock \
        "$(ls /tmp/wheels/deepcontact/*.whl)[bench,ray]" /tmp/wheels/box2d/*.whl \
    && pip uninstall --yes pip setuptools \
    && rm -rf /tmp/wheels /tmp/requirements.lock
COPY examples/ examples/
ENTRYPOINT ["deepcontact"]
CMD ["--help"]
