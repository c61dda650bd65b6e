# Multi-stage build of the Seamstress service.
#
#   docker build -t seamstress .
#   docker run -p 8080:8080 -v seamstress-data:/data \
#       -e SEAMSTRESS_TOKENS=alice:secret seamstress
#
# The server refuses to listen beyond loopback without bearer tokens; set
# SEAMSTRESS_TOKENS (or SEAMSTRESS_INSECURE_OPEN=true on a trusted network).

FROM rust:1.95-bookworm AS build
WORKDIR /src
# Dependencies first, so that a source change does not rebuild them.
COPY Cargo.toml Cargo.lock ./
RUN mkdir -p src benches \
    && echo 'fn main() {}' > src/main.rs \
    && touch src/lib.rs \
    && for b in erase seam_aware service bc1 farm; do echo 'fn main() {}' > benches/$b.rs; done \
    && cargo build --release --locked \
    && rm -rf src benches
COPY src ./src
COPY benches ./benches
COPY openapi.yaml ./
# The stub build left fresh fingerprints; make sure the real sources win.
RUN touch src/main.rs src/lib.rs && cargo build --release --locked --bin seamstress

FROM debian:bookworm-slim
RUN apt-get update \
    && apt-get install -y --no-install-recommends ca-certificates curl \
    && rm -rf /var/lib/apt/lists/* \
    && useradd --system --uid 10001 --home-dir /data --shell /usr/sbin/nologin seamstress \
    && mkdir -p /data && chown seamstress:seamstress /data
COPY --from=build /src/target/release/seamstress /usr/local/bin/seamstress
USER seamstress
VOLUME ["/data"]
EXPOSE 8080
ENV SEAMSTRESS_LISTEN=0.0.0.0:8080 \
    SEAMSTRESS_DATA=/data
HEALTHCHECK --interval=30s --timeout=5s --start-period=10s --retries=3 \
    CMD curl -fsS http://127.0.0.1:8080/healthz || exit 1
ENTRYPOINT ["seamstress"]
CMD ["serve"]
