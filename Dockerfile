# One image for every diffpos service (anchor, fusion, recorder, dashboard, emulate).
# The Zenoh router runs from the official eclipse/zenoh image (see docker-compose.yml),
# pinned to the same version as the eclipse-zenoh Python wheel in pyproject.toml.
#
#   docker build -t diffpos:local .
#   docker run --rm diffpos:local --help
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    DIFFPOS_LOG_FORMAT=json

WORKDIR /app
# packaging files first (change rarely), then the sources
COPY pyproject.toml setup.py README.md ./
COPY diffpos ./diffpos
COPY services ./services
COPY schemas ./schemas
COPY scenarios ./scenarios
# a regular (non-editable) install: setup.py's build hook ships schemas/ and scenarios/ inside
# the package (diffpos_services/_data, found by diffpos_services.resources)
RUN pip install . \
 && useradd --create-home --uid 10001 diffpos \
 && mkdir -p /data/recordings \
 && chown -R diffpos /data

USER diffpos
WORKDIR /data
ENTRYPOINT ["diffpos"]
CMD ["--help"]
