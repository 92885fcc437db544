# syntax=docker/dockerfile:1
# demq GPU worker image: `demq worker` claims jobs from the shared PostgreSQL queue and runs them on
# the one GPU the container is given (CUDA backend; the CPU backend when no GPU is visible).
#
# CUDA: the base image brings the CUDA 12 runtime; numba-cuda[cu12] brings NVVM/nvJitLink as pip
# wheels, so the "runtime" (not "devel") image is enough. The host needs the NVIDIA driver and the
# NVIDIA Container Toolkit (driver R570 or newer for CUDA 12.8). For CUDA 13:
#   --build-arg CUDA_IMAGE=nvidia/cuda:13.0.2-runtime-ubuntu24.04 --build-arg NUMBA_CUDA_EXTRA=cu13
#
# Build from the repository root (the build context must be the root):
#   docker build -f deploy/docker/worker.Dockerfile -t demq-worker .
# Run one worker per GPU:
#   docker run -d --gpus '"device=0"' -v demq-data:/data --stop-timeout 90 \
#     -e DEMQ_DATABASE_URL=postgresql://demq:PASSWORD@dbhost:5432/demq demq-worker
ARG CUDA_IMAGE=nvidia/cuda:12.8.1-runtime-ubuntu24.04
FROM ${CUDA_IMAGE}
ARG NUMBA_CUDA_EXTRA=cu12

ENV DEBIAN_FRONTEND=noninteractive \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    VIRTUAL_ENV=/opt/demq \
    PATH=/opt/demq/bin:$PATH \
    NVIDIA_VISIBLE_DEVICES=all \
    NVIDIA_DRIVER_CAPABILITIES=compute,utility \
    NUMBA_CACHE_DIR=/opt/demq-kernels \
    DEMQ_DATA_DIR=/data

# Ubuntu 24.04: Python 3.12. A virtual environment, because the system Python is externally managed.
RUN apt-get update \
 && apt-get install -y --no-install-recommends python3 python3-venv \
 && rm -rf /var/lib/apt/lists/* \
 && python3 -m venv /opt/demq

WORKDIR /src
COPY deploy/docker/constraints.txt /src/deploy/docker/constraints.txt
COPY pyproject.toml README.md /src/
COPY engine /src/engine
COPY jobs /src/jobs
COPY service /src/service
COPY bench /src/bench
# the postgres extra: the psycopg driver of the shared PostgreSQL queue (the light install has the SQLite one only)
RUN pip install --constraint /src/deploy/docker/constraints.txt "numba-cuda[${NUMBA_CUDA_EXTRA}]" "/src[postgres]" \
 && useradd --system --create-home --home-dir /home/demq demq \
 && mkdir -p /data /opt/demq-kernels \
 && chown demq:demq /data /opt/demq-kernels

USER demq
# Every kernel specialisation compiled into the image's kernel cache (NUMBA_CACHE_DIR), so a fresh container's
# first job loads instead of compiling. The build has no GPU: the CPU kernels; a worker on a GPU host compiles its
# CUDA kernels once at start-up, before its first claim (DEMQ_WORKER_WARM), into the same cache.
RUN demq warm --backend cpu
WORKDIR /data
VOLUME ["/data"]
# SIGTERM: the worker stops claiming, asks its simulation to stop (the last checkpoint is kept),
# releases the job's lease and exits 0. Give it --stop-timeout / stop_grace_period well above
# DEMQ_CANCEL_GRACE_SECONDS.
STOPSIGNAL SIGTERM
# The job table answers (the worker's own liveness is guarded by its lease: a hung or dead worker's
# job is requeued by the reaper of any other worker).
HEALTHCHECK --interval=60s --timeout=20s --start-period=60s --retries=3 \
  CMD ["demq", "status", "--local", "--limit", "1"]
CMD ["demq", "worker"]
