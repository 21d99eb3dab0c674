# One image for the API and the workers (docker-compose.yml chooses the command).
FROM python:3.11-slim-bookworm

# libllvm19: Dr.Jit's LLVM backend crashes with Debian's default LLVM 15.
RUN apt-get update \
 && apt-get install -y --no-install-recommends libllvm19 curl \
 && rm -rf /var/lib/apt/lists/*

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM-19.so \
    NDRF_STORE=/data/runs

WORKDIR /app
# The CPU wheel of torch first: an unpinned torch pulls several GB of CUDA packages. The compose
# profile "gpu" builds with TORCH_INDEX=https://pypi.org/simple: PyPI's default wheel, with CUDA.
ARG TORCH_INDEX=https://download.pytorch.org/whl/cpu
RUN pip install --no-cache-dir --index-url ${TORCH_INDEX} torch==2.13.0

COPY pyproject.toml README.md ./
COPY schemas/ schemas/
COPY services/ services/
COPY api/ api/
COPY worker/ worker/
COPY cli/ cli/
RUN pip install --no-cache-dir ".[s3]" \
 && useradd --uid 10001 --create-home ndrf \
 && mkdir -p /data/runs && chown -R ndrf /data

USER ndrf
EXPOSE 8000
CMD ["ndrf", "serve", "--host", "0.0.0.0", "--port", "8000"]
