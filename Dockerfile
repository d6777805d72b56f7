# seasonloc: multi-stage build from source; the runtime image holds only the binary.
#
# What the image runs (checked without a Docker engine by tests/service/docker.rs, which starts
# the binary with this file's ENV and runs this file's HEALTHCHECK command against it):
#   seasonloc serve   listening on 0.0.0.0:8080, store in the volume /data,
#   as the unprivileged user `seasonloc` (uid 10001), API keys from the secret file
#   /run/secrets/seasonloc-api-keys (the service refuses to start on 0.0.0.0 without it).
#
# The key file is JSON {"keys": [{"name", "role", "sha256"}]} holding only SHA-256 digests of
# the keys; mount it as a secret, never bake it into the image:
#   docker run -p 8080:8080 -v seasonloc-data:/data \
#     --mount type=bind,src=$PWD/keys.json,dst=/run/secrets/seasonloc-api-keys,readonly seasonloc
# (Compose/Swarm `secrets:` and Kubernetes secret volumes mount at the same path; send SIGHUP
# to the process after rotating the file.)

FROM rust:1.91-slim-bookworm AS build
WORKDIR /src
COPY Cargo.toml Cargo.lock ./
COPY src ./src
COPY benches ./benches
COPY migrations ./migrations
COPY openapi ./openapi
COPY assets ./assets
# Exactly the locked dependency tree; the image keeps symbol names (backtraces) but not the line
# tables of the release profile (45 MB instead of 195 MB).
RUN cargo build --release --locked --bin seasonloc --config 'profile.release.strip="debuginfo"'

FROM debian:bookworm-slim AS runtime
# uid and gid 10001: deploy/deployment.yaml runs the pod as this user and group.
RUN groupadd --system --gid 10001 seasonloc \
    && useradd --system --uid 10001 --gid 10001 --home-dir /nonexistent --shell /usr/sbin/nologin seasonloc \
    && mkdir -p /data && chown seasonloc /data
COPY --from=build /src/target/release/seasonloc /usr/local/bin/seasonloc
ENV SEASONLOC_ADDR=0.0.0.0:8080
ENV SEASONLOC_DATA_DIR=/data
ENV SEASONLOC_API_KEYS=/run/secrets/seasonloc-api-keys
ENV RUST_LOG=info
VOLUME /data
EXPOSE 8080
USER seasonloc
# bash's /dev/tcp needs no curl in the image.
HEALTHCHECK --interval=30s --timeout=3s --start-period=5s --retries=3 \
    CMD ["bash", "-c", "exec 3<>/dev/tcp/127.0.0.1/8080 && printf 'GET /healthz HTTP/1.0\\r\\n\\r\\n' >&3 && head -n 1 <&3 | grep -q ' 200 '"]
ENTRYPOINT ["seasonloc"]
CMD ["serve"]
