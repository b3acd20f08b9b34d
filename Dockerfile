# One image for every dmpc process: the plant, the agents (and, if wanted, `dmpc router`).
#
#   docker build -t dmpc:0.1.0 .
#   docker run --rm dmpc:0.1.0 validate scenarios/paper.yaml
#
# docker-compose.yml runs the paper's example from it; see docs/deploy.md.
FROM python:3.11-slim

ENV PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

WORKDIR /app
COPY pyproject.toml README.md ./
COPY dmpc ./dmpc
COPY agents ./agents
COPY plant ./plant
COPY coordinator ./coordinator
COPY bus ./bus
RUN pip install .
COPY scenarios ./scenarios

# run as an unprivileged user; run folders go to /runs (a volume in docker-compose.yml)
RUN useradd --create-home --uid 1000 dmpc && mkdir /runs && chown dmpc /runs
USER dmpc
VOLUME ["/runs"]

# the Zenoh port, for a plant or agent that listens (peer mode) or `dmpc router`
EXPOSE 7447/tcp

ENTRYPOINT ["dmpc"]
CMD ["--help"]
