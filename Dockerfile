# The planning service: python -m service (uvicorn on 0.0.0.0:8000, worker processes inside).
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

WORKDIR /app

# A C compiler for the compiled NLP functions (optimizer.native: the shooting NLP's CasADi code,
# compiled once and cached; without a compiler the service works, slower).
RUN apt-get update && apt-get install -y --no-install-recommends gcc libc6-dev \
    && rm -rf /var/lib/apt/lists/*

# Install the package (library + service, docs assets included as package data).
COPY pyproject.toml README.md ./
COPY optimizer ./optimizer
COPY service ./service
RUN pip install . && rm -rf /app/build

# Run as an unprivileged user.
RUN useradd --system --create-home --uid 10001 planner
USER planner
WORKDIR /home/planner

# The compiled shooting NLPs of the default robot of every joint count the warm-up prepares and
# the proofs' compiled quadrature, built into the image (service/prebuild.py): a worker's first
# plan of any of them loads its library (other robots' exponents are built on first use, in the
# background, into the same cache: ~/.cache/chained-planner/native).
RUN python -m service.prebuild

ENV PLANNER_HOST=0.0.0.0 \
    PLANNER_PORT=8000
EXPOSE 8000

HEALTHCHECK --interval=15s --timeout=5s --start-period=60s --retries=3 \
    CMD ["python", "-c", "import sys, urllib.request; sys.exit(0 if urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=4).status == 200 else 1)"]

CMD ["python", "-m", "service"]
