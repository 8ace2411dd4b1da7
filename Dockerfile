# GD2P service image: every service container runs `python -m services.<name>` from this image
# (see deploy/docker-compose.yml). CPU only.
#
#   docker build -t gd2p-zenoh:0.1.0 .
#   docker build --build-arg TORCH_INDEX_URL=<a CPU-only PyTorch wheel index> -t gd2p-zenoh:0.1.0 .
FROM python:3.11-slim

# Empty: pip's configured index. Pointing it at a CPU-only wheel index avoids pulling the
# multi-GB CUDA build of torch, which these CPU-first services never use.
ARG TORCH_INDEX_URL=""

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    OMP_NUM_THREADS=1

# torch first and alone, pinned: it is the largest layer and changes least often, and installing
# it before the project keeps the resolver from choosing another build for it.
RUN if [ -n "$TORCH_INDEX_URL" ]; then \
        pip install --index-url "$TORCH_INDEX_URL" torch==2.13.0; \
    else \
        pip install torch==2.13.0; \
    fi

WORKDIR /opt/gd2p
COPY pyproject.toml README.md ./
COPY shared ./shared
COPY visualisation ./visualisation
COPY client ./client
COPY services ./services
COPY deploy ./deploy
COPY cli ./cli
RUN pip install . \
    && useradd --create-home --uid 10001 --user-group gd2p \
    && mkdir -p /data/recordings \
    && chown -R gd2p:gd2p /data

# Services need no privileges; a named volume mounted on /data/recordings inherits this owner.
USER gd2p
WORKDIR /home/gd2p
CMD ["gd2p", "--help"]
