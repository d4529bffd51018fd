# deepcontact in a container: the same two-step set-up as on a workstation
# (`make setup` builds .venv and the patched Box2D wheel), then the CLI.
FROM python:3.11-slim-bookworm

RUN apt-get update \
    && apt-get install -y --no-install-recommends build-essential patch make \
    && rm -rf /var/lib/apt/lists/*

WORKDIR /app
# Dependencies and the Box2D build first, so code edits do not rebuild them.
COPY requirements.lock pyproject.toml setup.py README.md Makefile ./
COPY box2d/ box2d/
COPY deepcontact/ deepcontact/
COPY simclient/ simclient/
COPY server/ server/
COPY training/ training/
COPY bench/ bench/
COPY proto/ proto/
RUN make setup PYTHON=python3.11
COPY models/ models/

ENV PATH=/app/.venv/bin:$PATH PYTHONUNBUFFERED=1
ENTRYPOINT ["deepcontact"]
CMD ["--help"]
