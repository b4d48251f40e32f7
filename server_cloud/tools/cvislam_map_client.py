#!/usr/bin/python3
"""Fetches one map from a cvislam_server over cvislam.v1.MapService and writes its points as a PLY file.

A short client in another language than the server, to show the API is usable from anywhere gRPC is. It needs
Debian's python3-grpcio and python3-protobuf, and the Python stubs that the build generates (build/<preset>/python;
--stubs or CVISLAM_PY_STUBS point elsewhere).

  cvislam_map_client.py --server 127.0.0.1:50051 --mission overlap2 [--map 0] --out map.ply \
      [--token T | $CVISLAM_TOKEN] [--tls-ca ca.pem]

Exit status: 0 written, 1 the server refused or could not be reached, 2 bad arguments or missing stubs.
"""
import argparse
import os
import sys


def find_stubs(given):
    candidates = [given, os.environ.get("CVISLAM_PY_STUBS")]
    repo = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    candidates.append(os.path.join(repo, "build", "default", "python"))
    for c in candidates:
        if c and os.path.isfile(os.path.join(c, "cvislam", "v1", "map_service_pb2.py")):
            return c
    return None


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--server", default="127.0.0.1:50051", help="host:port [%(default)s]")
    parser.add_argument("--mission", required=True)
    parser.add_argument("--map", type=int, default=None, help="map id [the mission's largest map]")
    parser.add_argument("--out", required=True, help="PLY file to write")
    parser.add_argument("--stubs", help="folder of the generated Python stubs [build/default/python]")
    parser.add_argument("--timeout", type=float, default=30.0, help="seconds per call [%(default)s]")
    parser.add_argument("--token", default=os.environ.get("CVISLAM_TOKEN", ""),
                        help="the mission's token, when the server has a tokens file [$CVISLAM_TOKEN]")
    parser.add_argument("--tls-ca", help="speak TLS, trusting the server certificate's CA in this PEM file")
    args = parser.parse_args()
    if any(c <= " " or c > "~" for c in args.token):
        print("cvislam_map_client: --token may hold printable ASCII characters only, without spaces", file=sys.stderr)
        return 2

    stubs = find_stubs(args.stubs)
    if stubs is None:
        print("cvislam_map_client: no generated stubs (cvislam/v1/map_service_pb2.py): build the project "
              "(cmake --build --preset default) or pass --stubs DIR", file=sys.stderr)
        return 2
    sys.path.insert(0, stubs)
    try:
        import grpc
        from cvislam.v1 import map_service_pb2, map_service_pb2_grpc
    except ImportError as e:
        print("cvislam_map_client: %s (install python3-grpcio and python3-protobuf: deploy/install_deps.sh)" % e,
              file=sys.stderr)
        return 2

    if args.tls_ca:
        try:
            with open(args.tls_ca, "rb") as f:
                channel = grpc.secure_channel(args.server, grpc.ssl_channel_credentials(root_certificates=f.read()))
        except OSError as e:
            print("cvislam_map_client: --tls-ca: %s" % e, file=sys.stderr)
            return 2
    else:
        channel = grpc.insecure_channel(args.server)
    stub = map_service_pb2_grpc.MapServiceStub(channel)
    metadata = [("authorization", "Bearer " + args.token)] if args.token else None
    try:
        map_id = args.map
        if map_id is None:
            maps = stub.ListMaps(map_service_pb2.ListMapsRequest(mission=args.mission), timeout=args.timeout,
                                 metadata=metadata).maps
            if not maps:
                print("cvislam_map_client: mission %s has no map yet" % args.mission, file=sys.stderr)
                return 1
            map_id = max(maps, key=lambda m: m.keyframes).map_id
        points = []
        keyframes = 0
        chunks = 0
        last = False
        request = map_service_pb2.GetMapRequest(mission=args.mission, map_id=map_id)
        for chunk in stub.GetMap(request, timeout=args.timeout, metadata=metadata):
            chunks += 1
            keyframes += len(chunk.keyframes)
            points.extend((p.p_m.x, p.p_m.y, p.p_m.z, p.observations) for p in chunk.points)
            last = chunk.last
    except grpc.RpcError as e:
        print("cvislam_map_client: %s from %s: %s" % (e.code().name, args.server, e.details()), file=sys.stderr)
        return 1
    if not last:
        print("cvislam_map_client: the stream ended before its last chunk", file=sys.stderr)
        return 1

    with open(args.out, "w") as f:
        f.write("ply\nformat ascii 1.0\ncomment cvislam mission %s map %d\nelement vertex %d\n"
                "property float x\nproperty float y\nproperty float z\nproperty uint observations\nend_header\n"
                % (args.mission, map_id, len(points)))
        for x, y, z, n in points:
            f.write("%.5f %.5f %.5f %d\n" % (x, y, z, n))
    print("map %d of %s: %d keyframes, %d points in %d chunks -> %s"
          % (map_id, args.mission, keyframes, len(points), chunks, args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
