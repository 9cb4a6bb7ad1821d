"""Generated wire schema of n3dmap (`n3dmap.v1`, from proto/n3dmap/v1/*.proto by scripts/gen_proto.sh).

Only protobuf/gRPC stubs live here; the library is `core` and the services are `services`.
Do not edit the generated files by hand: change the .proto and rerun the script.
"""
