# The cvislam server image: cvislam_server, cvislam_mapctl, the shipped vocabulary and the live viewer's page with
# three.js, run as a non-root user.
#
#   docker build -f deploy/docker/server.Dockerfile -t cvislam-server .     (from the repository root)
#   docker run -p 50051:50051 -v cvislam-store:/var/lib/cvislam cvislam-server
#
# Stage 1 builds with the project's own dependency script and the release preset; stage 2 has only the shared
# libraries the binaries link. RUNTIME_PACKAGES is checked against the binaries' ELF NEEDED entries by
# test/deploy/container_files_test.py (CTest: deploy_container_server), so it cannot drift from the build.
FROM debian:12.8 AS build
WORKDIR /src
COPY deploy/install_deps.sh deploy/install_deps.sh
RUN deploy/install_deps.sh && rm -rf /var/lib/apt/lists/*
COPY . .
RUN cmake --preset release \
 && cmake --build --preset release --target cvislam_server cvislam_mapctl \
 && cmake --install build/release --component server --prefix /opt/cvislam
# three.js for the live viewer's page (--viewer-listen), from npm, beside the page the install put in share/cvislam.
RUN apt-get update && apt-get install -y --no-install-recommends nodejs npm && rm -rf /var/lib/apt/lists/* \
 && npm install --prefix /opt/cvislam/share/cvislam --no-audit --no-fund three@0.187.0

FROM debian:12.8-slim
ARG RUNTIME_PACKAGES="libabsl20220623 libpq5 libopenblas0-serial libcholmod3 libcxsparse3 libdeflate0 libgoogle-glog0v6 libgrpc++1.51 \
libgrpc29 libopencv-calib3d406 libopencv-core406 libprotobuf32 \
libprometheus-cpp-core1.0 libprometheus-cpp-pull1.0 libsqlite3-0 libyaml-cpp0.7 \
libssl3 libzstd1 liblz4-1 zlib1g"
RUN apt-get update \
 && apt-get install -y --no-install-recommends ${RUNTIME_PACKAGES} \
 && rm -rf /var/lib/apt/lists/* \
 && groupadd --gid 10001 cvislam \
 && useradd --uid 10001 --gid 10001 --no-create-home --shell /usr/sbin/nologin cvislam \
 && mkdir -p /var/lib/cvislam /etc/cvislam \
 && chown 10001:10001 /var/lib/cvislam
COPY --from=build /opt/cvislam /opt/cvislam
ENV PATH=/opt/cvislam/bin:${PATH}
USER 10001:10001
WORKDIR /var/lib/cvislam
# 50051: the agent link and the map service; 8765: the live viewer when started with --viewer-listen 0.0.0.0:8765.
EXPOSE 50051 8765
VOLUME ["/var/lib/cvislam"]
ENTRYPOINT ["/opt/cvislam/bin/cvislam_server"]
# The default command serves TLS with tokens, from files mounted at /etc/cvislam/secrets (where the Kubernetes
# Secret goes): on a reachable address the server refuses to start without them. On a network you trust, give
# your own arguments with --insecure instead.
CMD ["--listen", "0.0.0.0:50051", "--store", "/var/lib/cvislam/store.db", "--output", "/var/lib/cvislam/output", \
     "--tls-cert", "/etc/cvislam/secrets/tls.crt", "--tls-key", "/etc/cvislam/secrets/tls.key", \
     "--tokens", "/etc/cvislam/secrets/tokens"]
