# One image for every service of docker-compose.yml: the tupa command with everything installed.
FROM python:3.11-slim

WORKDIR /app
RUN apt-get update && apt-get install -y --no-install-recommends build-essential \
    && rm -rf /var/lib/apt/lists/*
# torch first (pinned, as in the Makefile), so that code changes do not reinstall it.
RUN pip install --no-cache-dir 'torch==2.13.0'
COPY pyproject.toml README.md ./
COPY sim ./sim
COPY policies ./policies
COPY service ./service
COPY api ./api
COPY closed_loop ./closed_loop
COPY sitl_mock ./sitl_mock
RUN pip install --no-cache-dir .

# No secrets baked in: TUPA_API_TOKEN comes from the environment (docker-compose.yml).
ENTRYPOINT ["tupa"]
CMD ["--help"]
