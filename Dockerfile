# syntax=docker/dockerfile:1
# Multi-stage build: compile in the Rust image, run from a slim Debian with only the binary.
#   docker build -t safedice .
#   docker run -p 8080:8080 -v safedice-data:/data -e SAFEDICE_API_TOKEN=change-me safedice
# The container listens on 0.0.0.0, so the server refuses to start without SAFEDICE_API_TOKEN
# (or SAFEDICE_INSECURE_PUBLIC=true). The gRPC service (docs/grpc.md) is off until asked for:
#   docker run -p 8080:8080 -p 8081:8081 -e SAFEDICE_GRPC_BIND=0.0.0.0:8081 ... safedice

FROM rust:1.95-bookworm AS build
WORKDIR /src
COPY . .
# Cache mounts keep the registry and build outputs between builds; the binary is copied out of
# the cached target directory in the same step.
RUN --mount=type=cache,target=/usr/local/cargo/registry \
    --mount=type=cache,target=/src/target \
    cargo build --release --locked --bin safedice \
    && cp target/release/safedice /usr/local/bin/safedice

FROM debian:bookworm-slim
RUN apt-get update \
    && apt-get install -y --no-install-recommends ca-certificates tini \
    && rm -rf /var/lib/apt/lists/* \
    && useradd --system --uid 10001 --user-group --home-dir /data --no-create-home safedice \
    && mkdir -p /data \
    && chown safedice:safedice /data
COPY --from=build /usr/local/bin/safedice /usr/local/bin/safedice
USER safedice:safedice
ENV SAFEDICE_BIND=0.0.0.0:8080 \
    SAFEDICE_DATA_DIR=/data \
    SAFEDICE_LOG_FORMAT=json
VOLUME ["/data"]
EXPOSE 8080
# The gRPC service's conventional port, when SAFEDICE_GRPC_BIND=0.0.0.0:8081 turns it on.
EXPOSE 8081
# tini forwards SIGTERM to the server (graceful shutdown) and reaps children.
ENTRYPOINT ["/usr/bin/tini", "--", "safedice"]
CMD ["serve"]
