# syntax=docker/dockerfile:1
# The cscsr image: the `cscsr` CLI plus `dask scheduler` / `dask worker`.
#
#   docker build -t cscsr:latest .                       # CPU torch (default)
#   docker build -t cscsr:gpu \
#       --build-arg TORCH_INDEX=https://download.pytorch.org/whl/cu126 .   # CUDA torch
#
# docker-compose.yml builds both (the gpu one only under `--profile gpu`).
FROM python:3.11-slim

# Which torch wheels to install: the CPU index by default (a plain `pip install torch`
# on Linux pulls gigabytes of CUDA libraries); pass a CUDA index for the gpu image.
ARG TORCH_INDEX=https://download.pytorch.org/whl/cpu
# UID/GID of the runtime user: match them to the owner of ./inbox and ./outbox on the host.
ARG UID=1000
ARG GID=1000

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

# opencv-python-headless needs no libGL; libglib2.0-0 covers its remaining shared-library
# needs. ffmpeg comes from the imageio-ffmpeg wheel.
RUN apt-get update \
    && apt-get install -y --no-install-recommends libglib2.0-0 \
    && rm -rf /var/lib/apt/lists/*

# Every version the host's `make` installs (constraints.txt, `make lock`), so the cluster
# runs the same Dask, zarr and numcodecs as the client.
COPY constraints.txt /etc/cscsr/constraints.txt

# torch first, pinned, from the chosen index; the project's "torch>=2.4" accepts it as is.
# Only torch comes from that index (--no-deps): its dependencies (and a CUDA build's nvidia-*
# libraries) come with the project below, from PyPI, at the constrained versions. The pin has
# no local label, so the CPU wheel (2.13.0+cpu) and a CUDA one (2.13.0+cu126) both satisfy it.
RUN pip install --no-cache-dir --no-deps -c /etc/cscsr/constraints.txt torch==2.13.0 --index-url ${TORCH_INDEX}

# The project; bokeh on top so the scheduler's dashboard (:8787) works (distributed
# serves it only when bokeh is installed; the project itself does not need it).
COPY . /src
RUN pip install --no-cache-dir -c /etc/cscsr/constraints.txt /src "bokeh>=3.1" && rm -rf /src

RUN groupadd --gid ${GID} cscsr \
    && useradd --uid ${UID} --gid ${GID} --create-home --shell /usr/sbin/nologin cscsr \
    && mkdir -p /data/inbox /data/outbox \
    && chown -R cscsr:cscsr /data

USER cscsr
WORKDIR /data

CMD ["cscsr", "--help"]
