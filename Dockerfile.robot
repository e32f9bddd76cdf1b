# A robot: the base install (numpy, OpenCV headless, Zenoh, zstd) and the ros extra (rosbags,
# pure Python) to read ROS bags and ROS 2 topics; nothing of the cloud side (pyproject's
# import contract: `fleetslam robot` imports no cloud module). docs/deployment.md "Containers".
#
#   docker build -f Dockerfile.robot -t fleetslam-robot .
#   docker run --rm -v /path/to/recordings:/recordings:ro fleetslam-robot \
#       robot --connect tcp/CLOUD:7447 --id r1 --source /recordings/lab_run.bag
#
# python:3.11-slim-bookworm as the cloud's (the same Python, glibc for OpenCV's and Zenoh's
# manylinux wheels; multi-arch, so also linux/arm64 for Raspberry-Pi-class robots).

# BASE: another image with Python 3.11 on PATH (python, pip) where Docker Hub is out of
# reach: --build-arg BASE=... (the container test takes FLEETSLAM_CONTAINER_BASE).
ARG BASE=docker.io/library/python:3.11-slim-bookworm

FROM ${BASE} AS requirements
COPY pyproject.toml /src/
RUN python -c "import tomllib; p = tomllib.load(open('/src/pyproject.toml', 'rb'))['project']; \
print('\n'.join(p['dependencies'] + p['optional-dependencies']['ros']))" > /requirements.txt

FROM ${BASE} AS wheel
WORKDIR /src
COPY pyproject.toml README.md ./
COPY src ./src
RUN pip wheel --no-cache-dir --no-deps --wheel-dir /wheels .

FROM ${BASE}
COPY --from=requirements /requirements.txt /tmp/requirements.txt
RUN pip install --no-cache-dir -r /tmp/requirements.txt && rm /tmp/requirements.txt
COPY --from=wheel /wheels /tmp/wheels
RUN pip install --no-cache-dir --no-deps /tmp/wheels/fleetslam-*.whl && rm -rf /tmp/wheels
RUN useradd --create-home --uid 1000 fleetslam && mkdir -p /data && chmod 1777 /data
ENV PYTHONUNBUFFERED=1
USER fleetslam
WORKDIR /data
ENTRYPOINT ["fleetslam"]
CMD ["robot", "--help"]
