"""The zenoh router configs: zenoh's own (strict) parser loads them, the files they name are where
the manifests mount them, and the TLS + access-control example really enforces what it says, with
n3dmap-style clients whose TLS settings ride in the `--connect` endpoint."""

from __future__ import annotations

import json
import shutil
import socket
import subprocess
import threading
import time
from pathlib import Path, PurePosixPath

import pytest
import zenoh

from tests.unit.deploy import manifests as m

TLS_CONFIG = m.ROOT / "deploy" / "zenoh" / "router-tls-acl.json5"


def test_zenoh_config_parser_is_strict():
    # What the next test relies on: a misspelt key is an error, not a silently ignored setting.
    with pytest.raises(zenoh.ZError, match="unknown field"):
        zenoh.Config.from_json5('{ mode: "router", lissen: { endpoints: ["tcp/0.0.0.0:7447"] } }')


@pytest.mark.parametrize("path", m.ZENOH_CONFIGS, ids=lambda p: p.name)
def test_router_config_loads_with_zenoh(path):
    try:
        conf = zenoh.Config.from_json5(path.read_text())
    except zenoh.ZError as e:
        raise AssertionError(f"{path.name}: zenoh rejects it: {e}") from None
    assert json.loads(conf.get_json("mode")) == "router", f"{path.name} is not a router config"
    assert json.loads(conf.get_json("listen/endpoints")), f"{path.name} listens nowhere"


def test_tls_files_are_where_kubernetes_mounts_them():
    conf = zenoh.Config.from_json5(TLS_CONFIG.read_text())
    tls = json.loads(conf.get_json("transport/link/tls"))
    files = [tls[k] for k in ("listen_private_key", "listen_certificate", "root_ca_certificate")]
    (router,) = [d for _, d in m.k8s_documents() if d.get("kind") == "Deployment"
                 and d["metadata"]["name"] == "zenoh-router"]
    pod = router["spec"]["template"]["spec"]
    (container,) = pod["containers"]
    volumes = {v["name"]: v for v in pod["volumes"]}
    secret_mounts = [v["mountPath"] for v in container["volumeMounts"] if "secret" in volumes[v["name"]]]
    for f in files:
        assert any(PurePosixPath(f).is_relative_to(mount) for mount in secret_mounts), (
            f"{TLS_CONFIG.name} reads {f}, but the zenoh-router pod mounts its certificate Secret at {secret_mounts}")
    config_arg = container["args"][container["args"].index("-c") + 1]
    config_mounts = [v["mountPath"] for v in container["volumeMounts"] if "configMap" in volumes[v["name"]]]
    assert any(PurePosixPath(config_arg).parent == PurePosixPath(mount) for mount in config_mounts), (
        f"zenohd reads {config_arg}, the ConfigMap is mounted at {config_mounts}")


# ----------------------------------------------------------------------------- TLS + ACL, for real

def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True)


def _make_certificates(directory: Path, names: list[str]) -> None:
    """A CA, and a key + certificate signed by it per name (CN n3dmap-<name>, valid for localhost)."""
    _openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.crt",
             "-days", "1", "-subj", "/CN=n3dmap-test-ca", cwd=directory)
    (directory / "san.cnf").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n")
    for name in names:
        _openssl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", f"{name}.key", "-out", f"{name}.csr",
                 "-subj", f"/CN=n3dmap-{name}", cwd=directory)
        _openssl("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.crt", "-CAkey", "ca.key", "-CAcreateserial",
                 "-out", f"{name}.crt", "-days", "1", "-extfile", "san.cnf", cwd=directory)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _client_endpoint(port: int, certs: Path, name: str) -> str:
    """The `--connect` endpoint a TLS client of the router passes (router-tls-acl.json5's header)."""
    return (f"tls/localhost:{port}#root_ca_certificate_file={certs}/ca.crt;"
            f"connect_certificate_file={certs}/{name}.crt;connect_private_key_file={certs}/{name}.key;enable_mtls=true")


def _wait_for(condition, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.05)
    return condition()


@pytest.mark.integration
@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command to make test certificates")
def test_tls_acl_router_enforces_the_roles(tmp_path):
    from services.streaming.session import ZenohOptions, open_session

    roles = ["router", "camera", "bridge", "listener", "viewer"]
    _make_certificates(tmp_path, roles)
    port = _free_port()
    text = TLS_CONFIG.read_text().replace("/etc/zenoh-certs", str(tmp_path))
    assert "tls/0.0.0.0:7448" in text
    router = zenoh.open(zenoh.Config.from_json5(text.replace("tls/0.0.0.0:7448", f"tls/127.0.0.1:{port}")))
    sessions = {}
    try:
        # The clients open sessions exactly as `n3dmap stream ... --mode client --connect ENDPOINT` does;
        # two listeners so that one can watch what the other tries to forge.
        for name in ("camera", "bridge", "listener", "listener2", "viewer"):
            cert = "listener" if name == "listener2" else name
            sessions[name] = open_session(ZenohOptions(mode="client", connect=(_client_endpoint(port, tmp_path, cert),)))
        received: dict[str, list[bytes]] = {"bridge": [], "listener": [], "viewer": []}
        lock = threading.Lock()

        def collect(who):
            def on_sample(sample):
                with lock:
                    received[who].append(sample.payload.to_bytes())
            return on_sample

        subs = [sessions["bridge"].declare_subscriber("n3dmap/*/rgbd", collect("bridge")),
                sessions["listener"].declare_subscriber("n3dmap/*/moving_objects", collect("listener")),
                sessions["viewer"].declare_subscriber("n3dmap/cam0/*", collect("viewer"))]   # as `stream view`
        token = sessions["bridge"].liveliness().declare_token("n3dmap/@bridge/b1")
        status = sessions["bridge"].declare_queryable("n3dmap/@bridge/b1/status",
                                                      lambda q: q.reply(q.key_expr, b'{"frames": 1}'))
        # The camera finds the bridge (what `stream camera --wait-for-bridge` does) ...
        assert _wait_for(lambda: any(r.ok for r in sessions["camera"].liveliness().get("n3dmap/@bridge/*", timeout=1.0))), \
            "the camera cannot see the bridge's liveliness token"
        # ... and the allowed traffic flows; wait for the subscriptions to reach the router first.
        assert _wait_for(lambda: (sessions["camera"].put("n3dmap/cam0/rgbd", b"frame") or True) and b"frame" in received["bridge"]), \
            "frames from the camera do not reach the bridge"
        assert _wait_for(lambda: (sessions["bridge"].put("n3dmap/cam0/moving_objects", b"boxes") or True)
                         and b"boxes" in received["listener"]), "results from the bridge do not reach the listener"
        assert _wait_for(lambda: b"frame" in received["viewer"] and b"boxes" in received["viewer"]), \
            f"the viewer does not get both frames and results: {received['viewer']}"
        assert _wait_for(lambda: any(r.ok for r in sessions["viewer"].liveliness().get("n3dmap/@bridge/*", timeout=1.0))), \
            "the viewer cannot see the bridge's liveliness token"
        replies = [r.ok.payload.to_bytes() for r in sessions["listener"].get("n3dmap/@bridge/*/status", timeout=2.0) if r.ok]
        assert replies == [b'{"frames": 1}'], f"the listener cannot query the bridge's status: {replies}"
        # Forgeries are dropped by the router.
        sessions["listener2"].put("n3dmap/cam0/rgbd", b"forged frame")
        sessions["camera"].put("n3dmap/cam0/moving_objects", b"forged boxes (camera)")
        sessions["listener2"].put("n3dmap/cam0/moving_objects", b"forged boxes (listener)")
        sessions["viewer"].put("n3dmap/cam0/rgbd", b"forged frame")
        sessions["viewer"].put("n3dmap/cam0/moving_objects", b"forged boxes (viewer)")
        sessions["bridge"].put("n3dmap/cam0/moving_objects", b"after")    # ordered after the forgeries
        assert _wait_for(lambda: b"after" in received["listener"])
        time.sleep(0.3)
        with lock:
            assert b"forged frame" not in received["bridge"], "a listener or viewer could publish frames"
            forged = [p for p in received["listener"] if p.startswith(b"forged")]
        assert not forged, f"the router let through {forged}"
        for declared in (*subs, token, status):
            declared.undeclare()
    finally:
        for session in sessions.values():
            session.close()
        router.close()
