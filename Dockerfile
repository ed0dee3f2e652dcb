# syntax=docker/dockerfile:1
# facegate: multi-stage build. Base images are build arguments so a mirror or a pinned digest
# can be used:  docker build --build-arg RUST_IMAGE=... --build-arg RUNTIME_IMAGE=... -t facegate .
ARG RUST_IMAGE=rust:1.95-slim-bookworm
ARG RUNTIME_IMAGE=debian:bookworm-slim

FROM ${RUST_IMAGE} AS build
WORKDIR /src
# The whole crate (see .dockerignore): Cargo checks every target listed in Cargo.toml.
COPY . .
RUN --mount=type=cache,target=/usr/local/cargo/registry \
    --mount=type=cache,target=/src/target \
    cargo build --release --locked --bin facegate \
    && install -m 0755 target/release/facegate /usr/local/bin/facegate

FROM ${RUNTIME_IMAGE}
# An unprivileged user owning only the database volume.
RUN groupadd --system --gid 10001 facegate \
    && useradd --system --uid 10001 --gid 10001 --home-dir /data --shell /usr/sbin/nologin facegate \
    && mkdir -p /data /sfm \
    && chown facegate:facegate /data
COPY --from=build /usr/local/bin/facegate /usr/local/bin/facegate
# The project's trained models (small, committed). Override with a volume on /opt/facegate/models
# or FACEGATE_MODELS. The Surrey Face Model (non-commercial licence) is not shipped: mount it at
# /sfm (read-only) for 3DMM pose correction; without it the service uses 2D alignment.
COPY models /opt/facegate/models
ENV FACEGATE_BIND=0.0.0.0:8080 \
    FACEGATE_DATABASE_URL=sqlite:///data/facegate.db \
    FACEGATE_MODELS=/opt/facegate/models \
    FACEGATE_SFM=/sfm \
    RUST_LOG=info
VOLUME ["/data"]
USER 10001:10001
WORKDIR /data
EXPOSE 8080
# The binary probes its own /health: the runtime image needs no curl.
HEALTHCHECK --interval=30s --timeout=5s --start-period=20s --retries=3 \
    CMD ["facegate", "serve", "--healthcheck"]
ENTRYPOINT ["facegate"]
CMD ["serve"]
