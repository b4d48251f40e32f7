# The cvislam agent image (x86-64; boards take the cross-built binary, see docs/deploy.md, "Building for a board"):
# cvislam_agent (with cvislam_sensor_publisher and cvislam_state_monitor for live topics) and its configs, run as a
# non-root user. The agent embeds RouDi, so the container needs a
# /dev/shm of at least 256 MiB (docker run --shm-size=256m; on Kubernetes a memory emptyDir, see
# deploy/k8s/base/agent-pod.yaml).
#
#   docker build -f deploy/docker/agent.Dockerfile -t cvislam-agent .       (from the repository root)
#   docker run --shm-size=256m -v /data/V1_01_easy:/data:ro cvislam-agent \
#     --dataset /data --output /tmp/out --server cvislam-server:50051 --mission m1 --agent-id 0
#
# RUNTIME_PACKAGES is checked against the binary's ELF NEEDED entries by test/deploy/container_files_test.py
# (CTest: deploy_container_agent).
FROM debian:12.8 AS build
WORKDIR /src
COPY deploy/install_deps.sh deploy/install_deps.sh
RUN deploy/install_deps.sh && rm -rf /var/lib/apt/lists/*
COPY . .
RUN cmake --preset release \
 && cmake --build --preset release --target cvislam_agent cvislam_sensor_publisher cvislam_state_monitor \
 && cmake --install build/release --component agent --prefix /opt/cvislam

FROM debian:12.8-slim
ARG RUNTIME_PACKAGES="libabsl20220623 libopenblas0-serial libcholmod3 libcxsparse3 libdeflate0 libgoogle-glog0v6 libgrpc++1.51 \
libgrpc29 libiceoryx-hoofs2 libiceoryx-posh-roudi2 libiceoryx-posh2 liblz4-1 libopencv-calib3d406 libopencv-core406 \
libprotobuf32 libyaml-cpp0.7 libzstd1 zlib1g"
RUN apt-get update \
 && apt-get install -y --no-install-recommends ${RUNTIME_PACKAGES} \
 && rm -rf /var/lib/apt/lists/* \
 && groupadd --gid 10001 cvislam \
 && useradd --uid 10001 --gid 10001 --no-create-home --shell /usr/sbin/nologin cvislam
COPY --from=build /opt/cvislam /opt/cvislam
ENV PATH=/opt/cvislam/bin:${PATH}
USER 10001:10001
WORKDIR /tmp
ENTRYPOINT ["/opt/cvislam/bin/cvislam_agent"]
CMD ["--help"]
