"""The committed stubs are exactly what scripts/gen_proto.sh generates from the .proto files."""

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]
GENERATED = ("types_pb2.py", "types_pb2.pyi", "types_pb2_grpc.py",
             "inference_pb2.py", "inference_pb2.pyi", "inference_pb2_grpc.py")


def test_regenerating_gives_the_committed_stubs(tmp_path):
    # this interpreter's grpc_tools, whether or not its venv is activated
    subprocess.run(["bash", str(ROOT / "scripts" / "gen_proto.sh"), str(tmp_path)], check=True, cwd=ROOT,
                   env={**os.environ, "PYTHON": sys.executable})
    for name in GENERATED:
        fresh = (tmp_path / "n3dmap" / "v1" / name).read_bytes()
        committed = (ROOT / "n3dmap" / "v1" / name).read_bytes()
        assert fresh == committed, f"n3dmap/v1/{name} is stale: run scripts/gen_proto.sh"


def test_generated_imports_are_package_paths():
    text = (ROOT / "n3dmap" / "v1" / "inference_pb2_grpc.py").read_text()
    assert "from n3dmap.v1 import inference_pb2" in text
    from n3dmap.v1 import inference_pb2
    assert inference_pb2.DESCRIPTOR.services_by_name["Inference"].full_name == "n3dmap.v1.Inference"
