# yauyau: the Yau-Yau real-time nonlinear filter as an HTTP service.
# Build stage: install into a virtual environment and precompute the bundled example models
# (scripts/provision.py, the same steps `python3 dev.py serve` and tests/service/test_service_provision.py run).
FROM python:3.11-slim AS build
ENV PIP_NO_CACHE_DIR=1 PYTHONDONTWRITEBYTECODE=1
WORKDIR /src
COPY pyproject.toml README.md ./
COPY yauyau ./yauyau
COPY solver ./solver
COPY storage ./storage
COPY service ./service
COPY scripts ./scripts
COPY examples ./examples
RUN python3 scripts/provision.py install --venv /opt/venv \
 && python3 scripts/provision.py precompute --venv /opt/venv --store /opt/store \
        examples/cubic_sensor.toml examples/ou.toml examples/benes.toml examples/range_2d.toml \
        examples/power_meter.toml

# Runtime stage: the virtual environment, the store (read-only) and the script; no build tools.
# The server listens on every interface of the container's own network (what a published port reaches):
# without a tenants file that needs YAUYAU_INSECURE_BIND, so publish on the host's loopback only
# (docker run -p 127.0.0.1:8000:8000) or mount a tenants file and set YAUYAU_TENANTS_FILE (docs/service.md, Docker).
FROM python:3.11-slim
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 \
    YAUYAU_STORE=/opt/store YAUYAU_SESSION_DB=/var/lib/yauyau/sessions.sqlite3 YAUYAU_HOST=0.0.0.0 \
    YAUYAU_PORT=8000 YAUYAU_INSECURE_BIND=true
RUN useradd --system --uid 10001 --home-dir /var/lib/yauyau --create-home yauyau
COPY --from=build /opt/venv /opt/venv
COPY --from=build /opt/store /opt/store
COPY scripts/provision.py /opt/yauyau/provision.py
USER 10001
WORKDIR /var/lib/yauyau
EXPOSE 8000
HEALTHCHECK --interval=30s --timeout=3s --start-period=30s --retries=3 \
    CMD ["/opt/venv/bin/python", "-c", "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/livez', timeout=2)"]
CMD ["python3", "/opt/yauyau/provision.py", "serve", "--venv", "/opt/venv", "--store", "/opt/store", "--host", "0.0.0.0", "--port", "8000"]
