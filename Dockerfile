# The cloud and the operator's tools: the base install, the cloud extra and etcd (for many
# workers). docs/deployment.md "Containers" says how to build and run it.
#
#   docker build -t fleetslam-cloud .
#   docker run --rm -p 7447:7447 -v "$PWD/store:/data/store" fleetslam-cloud
#   docker run --rm -v "$PWD/runs:/data/runs" fleetslam-cloud demo
#
# python:3.11-slim-bookworm: the Python the project is tested with, glibc for the manylinux
# wheels (GTSAM, small_gicp, faiss, OpenCV, Zenoh), and Debian 12's etcd-server (3.4), the
# etcd scripts/setup-system.sh installs. Multi-stage: etcd and the wheel come from stages of
# their own, and the dependencies are installed in a layer that changes only with
# pyproject.toml.

# BASE: another image with Python 3.11 on PATH (python, pip) where Docker Hub is out of
# reach: --build-arg BASE=... (the container test takes FLEETSLAM_CONTAINER_BASE).
ARG BASE=docker.io/library/python:3.11-slim-bookworm

FROM ${BASE} AS requirements
COPY pyproject.toml /src/
RUN python -c "import tomllib; p = tomllib.load(open('/src/pyproject.toml', 'rb'))['project']; \
print('\n'.join(p['dependencies'] + p['optional-dependencies']['cloud']))" > /requirements.txt

FROM ${BASE} AS wheel
WORKDIR /src
COPY pyproject.toml README.md ./
COPY src ./src
RUN pip wheel --no-cache-dir --no-deps --wheel-dir /wheels .

# Debian 12's etcd (3.4): one binary linked to libc alone, taken without apt's lists and
# caches or the package's service (fleetslam starts its own etcd per run).
FROM ${BASE} AS etcd
RUN apt-get update \
    && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends etcd-server

FROM ${BASE}
COPY --from=etcd /usr/bin/etcd /usr/local/bin/etcd
COPY --from=requirements /requirements.txt /tmp/requirements.txt
RUN pip install --no-cache-dir -r /tmp/requirements.txt && rm /tmp/requirements.txt
COPY --from=wheel /wheels /tmp/wheels
RUN pip install --no-cache-dir --no-deps /tmp/wheels/fleetslam-*.whl && rm -rf /tmp/wheels
# Any --user may run it: /data is everyone's, matplotlib's cache goes to /tmp.
RUN useradd --create-home --uid 1000 fleetslam && mkdir -p /data && chmod 1777 /data
ENV MPLCONFIGDIR=/tmp/matplotlib PYTHONUNBUFFERED=1
USER fleetslam
WORKDIR /data
EXPOSE 7447
ENTRYPOINT ["fleetslam"]
CMD ["cloud", "--listen", "tcp/0.0.0.0:7447", "--out", "/data/store"]
