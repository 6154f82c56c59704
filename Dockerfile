# trustlab behind PostgreSQL: `docker compose up` (see README.md and docker-compose.yml).

# Front-end libraries from the npm registry, pinned by package-lock.json.
FROM node:20-slim AS assets
WORKDIR /build
COPY package.json package-lock.json ./
RUN npm ci --ignore-scripts --no-audit --no-fund --loglevel=error \
 && mkdir -p vendor \
 && cp node_modules/htmx.org/dist/htmx.min.js node_modules/htmx-ext-sse/dist/sse.min.js \
       node_modules/plotly.js-cartesian-dist-min/plotly-cartesian.min.js \
       node_modules/swagger-ui-dist/swagger-ui-bundle.js node_modules/swagger-ui-dist/swagger-ui.css \
       vendor/ \
 && mkdir -p vendor/three \
 && cp node_modules/three/build/three.module.js node_modules/three/build/three.core.js \
       node_modules/three/LICENSE vendor/three/

FROM python:3.11-slim
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 PIP_DISABLE_PIP_VERSION_CHECK=1
RUN apt-get update \
 && apt-get install -y --no-install-recommends postgresql-client espeak-ng \
 && rm -rf /var/lib/apt/lists/* \
 && useradd --system --create-home --home-dir /srv/trustlab trustlab
WORKDIR /srv/trustlab
COPY requirements.lock ./
# torch==2.13.0 resolves to the CPU build from PyTorch's index (PyPI's default is a CUDA build).
RUN pip install --no-cache-dir --extra-index-url https://download.pytorch.org/whl/cpu -r requirements.lock
COPY --chown=trustlab . .
COPY --from=assets --chown=trustlab /build/vendor static/vendor
RUN pip install --no-cache-dir --no-deps -e . && mkdir -p var && chown trustlab var
USER trustlab
EXPOSE 8000
HEALTHCHECK --interval=10s --timeout=3s --start-period=30s --retries=5 \
  CMD python -c "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=2)"
CMD ["sh", "-c", "trustlab init && exec trustlab serve --host 0.0.0.0 --port 8000 --workers ${TRUSTLAB_WORKERS:-2}"]
