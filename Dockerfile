# armserver: the REST/WebSocket arm server. Default: the two simulated arms (no hardware).
# Hardware: pass the device through and mount a config file (see docker-compose.yml).
FROM python:3.11-slim

# hidapi's wheel bundles its library; libusb/udev are only needed for the hidraw backend.
RUN apt-get update \
    && apt-get install -y --no-install-recommends libusb-1.0-0 libudev1 \
    && rm -rf /var/lib/apt/lists/*

WORKDIR /srv/armserver
COPY pyproject.toml README.md* ./
COPY protocol ./protocol
COPY kinematics ./kinematics
COPY app ./app
# gcc for the poll thread's rounds in C (app/links/_restpoll.c; the image's Python has its
# headers), removed again once the package is built.
RUN apt-get update \
    && apt-get install -y --no-install-recommends gcc libc6-dev \
    && pip install --no-cache-dir . \
    && apt-get purge -y --auto-remove gcc libc6-dev \
    && rm -rf /var/lib/apt/lists/* \
    && useradd --system --uid 10001 --groups dialout armserver

USER armserver
ENV ARMSERVER_LOG_LEVEL=info
EXPOSE 8000
HEALTHCHECK --interval=10s --timeout=3s --start-period=10s \
    CMD python -c "import urllib.request,sys; urllib.request.urlopen('http://127.0.0.1:8000/api/v1/health', timeout=2)" || exit 1
# 0.0.0.0 inside the container: the host decides what reaches it (ports: in compose).
CMD ["armserver", "serve", "--host", "0.0.0.0", "--port", "8000"]
