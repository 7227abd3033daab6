# One image for every bodynet service of docker-compose.yml (gateway, nodes,
# recorder, viewer, game); the command picks the service, e.g.
#   docker run --rm bodynet gateway --mode client -e tcp/router:7447
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 \
    NUMBA_CACHE_DIR=/var/cache/bodynet
WORKDIR /src
COPY . .
# the gateway's kernels compiled once here, into a cache every user reads (numba
# takes a cache only where it may write: a run with no writable place compiles them)
RUN pip install . && mkdir -m 1777 /var/cache/bodynet \
    && python -c 'import bodynet.gateway.kernels' && rm -rf /src

# recordings and game results are health data: a user of its own, files 0600
RUN useradd --create-home --uid 1000 bodynet && mkdir /data && chown bodynet /data
USER bodynet
WORKDIR /data
ENTRYPOINT ["bodynet"]
CMD ["--help"]
