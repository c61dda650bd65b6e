# Multi-stage build of the Seamstress service.
#
#   docker build -t seamstress .
#   docker run -p 8080:8080 -v seamstress-data:/data \
#       -e SEAMSTRESS_TOKENS=alice:secret seamstress
#
# The server refuses to listen beyond loopback without bearer tokens; set
# SEAMSTRESS_TOKENS (or SEAMSTRESS_INSECURE_OPEN=true on a trusted network).
# compose.yaml runs the image as a cluster: API servers and workers over
# PostgreSQL and an S3 store.

FROM rust:1.95-bookworm AS build
WORKDIR /src
# Dependencies first, so that a source change does not rebuild them: the
# real manifest over stub sources. Cargo loads every [[bench]] target that
# Cargo.toml names (autobenches is off) and fails on a missing file, so each
# gets a stub; the names are read from Cargo.toml, so that a new bench needs
# no change here. (No [[test]] or [[example]] is named there: tests/ and
# examples/ are found automatically, and left out of the image.) Cargo
# loads every path dependency, dev ones too: the tests' `needs` macro is
# copied for that, though no release build compiles it.
COPY Cargo.toml Cargo.lock ./
COPY tests/needs ./tests/needs
RUN mkdir -p src benches \
    && echo 'fn main() {}' > src/main.rs \
    && touch src/lib.rs \
    && benches=$(awk '/^\[/ { bench = ($0 ~ /^\[\[bench\]\]/); next } \
            bench && /^name *=/ { sub(/^name *= *"/, ""); sub(/".*/, ""); print }' Cargo.toml) \
    && for b in $benches; do echo 'fn main() {}' > "benches/$b.rs"; done \
    && cargo build --release --locked \
    && rm -rf src benches
COPY src ./src
COPY benches ./benches
# Compiled in: the PostgreSQL job store's migrations (sqlx::migrate!), the
# API description the server serves, and the view page with its three.js
# (include_str!, include_bytes!).
COPY migrations ./migrations
COPY openapi.yaml ./
COPY assets ./assets
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
# 8080: the API (serve); 9090: a worker's /metrics and /healthz, when its
# --metrics-listen says so (it stays on loopback by default).
EXPOSE 8080 9090
ENV SEAMSTRESS_LISTEN=0.0.0.0:8080 \
    SEAMSTRESS_DATA=/data
# For `serve` on the default port; a `worker` container needs its own
# check, on its metrics port (as compose.yaml gives it).
HEALTHCHECK --interval=30s --timeout=5s --start-period=10s --retries=3 \
    CMD curl -fsS http://127.0.0.1:8080/healthz || exit 1
ENTRYPOINT ["seamstress"]
CMD ["serve"]
