# syntax=docker/dockerfile:1
# demq API image: the HTTP API only (`demq serve --no-worker`); workers run in the worker image.
# No CUDA here: the API validates specs, serves results and never runs a simulation.
#
# Build from the repository root (the build context must be the root):
#   docker build -f deploy/docker/api.Dockerfile -t demq-api .
# Run (PostgreSQL queue, results on a volume shared with the workers):
#   docker run -d -p 8000:8000 -v demq-data:/data \
#     -e DEMQ_DATABASE_URL=postgresql://demq:PASSWORD@dbhost:5432/demq demq-api
FROM python:3.12-slim-bookworm

ENV PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    DEMQ_DATA_DIR=/data \
    DEMQ_HOST=0.0.0.0 \
    DEMQ_PORT=8000

WORKDIR /src
COPY deploy/docker/constraints.txt /src/deploy/docker/constraints.txt
COPY pyproject.toml README.md /src/
COPY engine /src/engine
COPY jobs /src/jobs
COPY service /src/service
COPY bench /src/bench
# the postgres extra: the psycopg driver of the shared PostgreSQL queue (the light install has the SQLite one only)
RUN pip install --constraint /src/deploy/docker/constraints.txt "/src[postgres]" \
 && useradd --system --create-home --home-dir /home/demq demq \
 && mkdir -p /data \
 && chown demq:demq /data

USER demq
WORKDIR /data
VOLUME ["/data"]
EXPOSE 8000
STOPSIGNAL SIGTERM
HEALTHCHECK --interval=30s --timeout=5s --start-period=30s --retries=3 \
  CMD ["python", "-c", "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:%s/healthz' % os.environ.get('DEMQ_PORT', '8000'), timeout=4)"]
CMD ["demq", "serve", "--no-worker"]
