# fleetmap: API and worker image. The install steps mirror .ci/run: torch first (CPU by default),
# then the package itself.
#   docker build -t fleetmap .                                   # CPU torch
#   docker build --build-arg TORCH_INDEX_URL=<CUDA wheel index> -t fleetmap:cuda .   # GPU workers
FROM python:3.11-slim

ARG TORCH_VERSION=2.13.0
# Index that serves the wanted torch build; the default is PyTorch's CPU-only wheel index.
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    FLEETMAP_DATA_DIR=/data

RUN apt-get update \
    && apt-get install -y --no-install-recommends libgomp1 curl \
    && rm -rf /var/lib/apt/lists/*

WORKDIR /app
RUN python -m pip install --upgrade pip \
    && python -m pip install "torch==${TORCH_VERSION}" --extra-index-url "${TORCH_INDEX_URL}"

COPY pyproject.toml README.md ./
COPY fusion ./fusion
COPY service ./service
COPY worker ./worker
COPY migrations ./migrations
RUN python -m pip install .

RUN useradd --create-home --uid 1000 fleetmap && mkdir -p /data && chown fleetmap /data
USER fleetmap
VOLUME ["/data"]
EXPOSE 8000

HEALTHCHECK --interval=10s --timeout=3s --retries=5 CMD curl -fsS http://127.0.0.1:8000/healthz || exit 1
CMD ["fleetmap", "serve", "--host", "0.0.0.0", "--port", "8000"]
