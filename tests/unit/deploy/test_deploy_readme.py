"""README "Running on a cluster": every command it tells the user to type parses with the real CLI it
runs (n3dmap, ray), every file it names exists, and every deployment file is documented."""

from __future__ import annotations

import re
import shlex

import pytest

from tests.unit.deploy import manifests as m

START, END = "## Running on a cluster", "## Development"
N3DMAP_AREAS = "data|train|jobs|bundle|eval|bench|serve|stream"


def cluster_section() -> str:
    text = (m.ROOT / "README.md").read_text()
    assert START in text and END in text, f"README.md lacks the '{START}' section"
    return text.split(START, 1)[1].split(END, 1)[0]


def _code_lines() -> list[str]:
    """Lines of the section's fenced code blocks (where the commands to type are)."""
    blocks = re.findall(r"```[a-z]*\n(.*?)```", cluster_section(), flags=re.S)
    return [line.strip() for block in blocks for line in block.splitlines() if line.strip()]


def _strip_comment(line: str) -> str:
    return re.split(r"\s+#\s", line, maxsplit=1)[0].rstrip(" &")


def readme_n3dmap_commands() -> list[m.Command]:
    """`n3dmap ...` wherever it is run: alone, after `kubectl exec ... --`, `docker compose exec SERVICE`,
    and `docker compose run --rm SERVICE ARGS` (the service's ENTRYPOINT is n3dmap)."""
    services = {name for name, s in m.compose()["services"].items()
                if m.is_n3dmap_image(s.get("image")) and "entrypoint" not in s}
    out = []
    for line in map(_strip_comment, _code_lines()):
        match = re.search(rf"(?:^|\s)n3dmap\s+((?:{N3DMAP_AREAS})\b.*)$", line)
        if match:
            out.append(m.Command(f"README `{line}`", shlex.split(match.group(1)), None))
            continue
        match = re.search(r"\bcompose\b.*\brun\s+--rm\s+(\S+)\s+(.*)$", line)
        if match and match.group(1) in services:
            out.append(m.Command(f"README `{line}`", shlex.split(match.group(2)), None))
    return out


def readme_ray_commands() -> list[m.Command]:
    out = []
    for line in map(_strip_comment, _code_lines()):
        match = re.match(r"^(?:\w+=\S+\s+)*ray\s+(.*)$", line)
        if match:
            out.append(m.Command(f"README `{line}`", shlex.split(match.group(1)), None))
    return out


def test_section_is_written():
    section = cluster_section()
    assert "CLUSTER_PLACEHOLDER" not in section
    for step in ("ray start --head", "--address", "n3dmap jobs", "RAY_AUTH_MODE", "kubectl apply", "docker compose"):
        assert step in section, f"README cluster section never shows {step!r}"


def test_readme_has_commands_to_check():
    assert len(readme_n3dmap_commands()) >= 10
    assert len(readme_ray_commands()) >= 3


@pytest.mark.parametrize("command", readme_n3dmap_commands(), ids=lambda c: c.where)
def test_readme_n3dmap_command_parses(command):
    args, _ = m.parse_n3dmap(command.argv, command.where)
    if getattr(args, "address", None):
        dashboard = m.parse_ray(["start", "--head"], "ray defaults")["dashboard_port"]
        assert args.address.endswith(f":{dashboard}"), f"{command.where}: --address must be the Ray Jobs port {dashboard}"


@pytest.mark.parametrize("command", readme_ray_commands(), ids=lambda c: c.where)
def test_readme_ray_command_parses(command):
    m.parse_ray(command.argv, command.where)


def test_files_named_exist_and_every_deployment_file_is_documented():
    section = cluster_section()
    named = set(re.findall(r"\b((?:deploy|docker)/[\w./-]*\w)", section))
    # The compose volume directories are the user's to create: they must be the compose bind mounts.
    volumes = {(m.COMPOSE.parent / v.split(":")[0]).resolve().relative_to(m.ROOT).as_posix()
               for s in m.compose()["services"].values() for v in s.get("volumes", []) if v.startswith("./volumes/")}
    for path in named:
        if path.startswith("deploy/compose/volumes"):
            assert path == "deploy/compose/volumes" or any(
                v.startswith(path + "/") or path == v or path.startswith(v + "/") for v in volumes), (
                f"README names {path}, on none of the compose mounts {sorted(volumes)}")
            continue
        assert (m.ROOT / path).exists(), f"README names {path}, which does not exist"
    files = [*m.DOCKERFILES.values(), m.COMPOSE, *m.K8S_DIR.glob("*.yaml"), *m.ZENOH_CONFIGS]
    for path in files:
        relative = path.relative_to(m.ROOT).as_posix()
        assert relative in section, f"README's cluster section never mentions {relative}"


def test_kubectl_names_match_the_manifests():
    """Secrets, Services, ConfigMaps and labels the README's kubectl lines use are the manifests' own."""
    docs = [d for _, d in m.k8s_documents()]
    names = {(d["kind"], d["metadata"]["name"]) for d in docs}
    text = "\n".join(_code_lines())
    for service in re.findall(r"svc/([\w-]+)", text):
        known = {n for k, n in names if k == "Service"} | {"n3dmap-ray-head-svc"}  # KubeRay names the head Service
        assert service in known, f"README port-forwards svc/{service}, not a Service of deploy/k8s"
    for kind, name in re.findall(r"\b(rayjob|deployment)[/ ]([\w-]+)", text):
        assert (kind.replace("rayjob", "RayJob").replace("deployment", "Deployment"), name) in names, (
            f"README names {kind} {name}, not in deploy/k8s")
    manifest_text = "\n".join(p.read_text() for p in m.K8S_DIR.glob("*.yaml"))
    for secret in re.findall(r"create secret generic ([\w-]+)", text):
        assert secret in manifest_text, f"README creates Secret {secret}, which no manifest reads"
    for configmap in re.findall(r"create configmap ([\w-]+)", text):
        assert f"name: {configmap}" in manifest_text, f"README creates ConfigMap {configmap}, which no manifest mounts"
