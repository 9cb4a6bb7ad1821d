"""The Dockerfiles install n3dmap through its pyproject, pin what pyproject pins, run as a non-root
user through the `n3dmap` CLI, and their healthcheck/EXPOSE match `n3dmap serve`'s defaults. Also the
environment variables and uids the manifests set, and the .dockerignore. No Docker engine needed."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.unit.deploy import manifests as m

IMAGES = sorted(m.DOCKERFILES)


def _stages(path: Path) -> dict[int, list[m.Instruction]]:
    out: dict[int, list[m.Instruction]] = {}
    for ins in m.dockerfile_instructions(path):
        out.setdefault(ins.stage, []).append(ins)
    return out


def _final(path: Path) -> list[m.Instruction]:
    stages = _stages(path)
    return stages[max(stages)]


def _one(instructions: list[m.Instruction], keyword: str) -> m.Instruction:
    found = [i for i in instructions if i.keyword == keyword]
    assert len(found) == 1, f"expected one {keyword}, found {len(found)}"
    return found[0]


@pytest.mark.parametrize("image", IMAGES)
def test_multi_stage_non_root_and_copies_only_the_venv(image):
    path = m.DOCKERFILES[image]
    stages = _stages(path)
    assert len([s for s in stages if s >= 0]) >= 2, f"{path.name} is not multi-stage"
    final = _final(path)
    user = _one(final, "USER").value
    assert user not in ("root", "0") and not user.startswith("0:"), f"{path.name} runs as {user}"
    copies = [i.value for i in final if i.keyword == "COPY"]
    assert copies and all(c.startswith("--from=") for c in copies), (
        f"{path.name}: the runtime stage should take only the builder's venv, copies {copies}")


@pytest.mark.parametrize("image", IMAGES)
def test_installs_everything_pyproject_installs_with_pip_install_dot(image):
    path = m.DOCKERFILES[image]
    builder = _stages(path)[0]
    copied: set[str] = set()
    install_at = None
    for index, ins in enumerate(builder):
        if ins.keyword == "COPY":
            *sources, _dest = ins.value.split()
            copied.update(s.rstrip("/") for s in sources if not s.startswith("--"))
        if ins.keyword == "RUN" and re.search(r"\bpip install (\S+ )*\.(\s|$)", ins.value):
            install_at = index
            break
        assert not (ins.keyword == "RUN" and "pip install -e" in ins.value), f"{path.name}: editable install"
    assert install_at is not None, f"{path.name}: the builder never runs `pip install .`"
    needed = {"pyproject.toml", m.pyproject()["project"]["readme"], *m.pyproject_package_dirs()}
    missing = needed - copied
    assert not missing, (f"{path.name}: `pip install .` runs before COPYing {sorted(missing)} — pyproject's "
                         f"packages.find includes {m.pyproject_package_dirs()}")
    # And nothing is installed around the pyproject (a second, drifting list of requirements).
    for ins in builder:
        if ins.keyword == "RUN" and "pip install" in ins.value and "torch==" not in ins.value:
            assert re.search(r"\bpip install \.", ins.value), f"{path.name}: installs outside the pyproject: {ins.value}"


@pytest.mark.parametrize("image", IMAGES)
def test_torch_pinned_to_pyprojects_version(image):
    path = m.DOCKERFILES[image]
    args = m.dockerfile_args(path)
    pin = m.pinned_requirement("torch")
    installs = [m.expand_args(i.value, args) for i in m.dockerfile_instructions(path)
                if i.keyword == "RUN" and "torch" in i.value]
    assert installs, f"{path.name} does not install torch first"
    assert all(f'"torch=={pin}"' in run or f"torch=={pin} " in run for run in installs), (
        f"{path.name}: torch is not pinned to pyproject's torch=={pin}: {installs}")


def test_both_images_share_the_python_base():
    # A Ray cluster refuses nodes whose Python differs from the head's; raycluster.yaml mixes them.
    bases = {image: m.dockerfile_args(path)["PYTHON_IMAGE"] for image, path in m.DOCKERFILES.items()}
    assert len(set(bases.values())) == 1, f"the images use different Python bases: {bases}"
    (base,) = set(bases.values())
    version = re.search(r":(\d+)\.(\d+)\.(\d+)", base)
    assert version, f"base image {base} is not pinned to a full Python version"
    low = re.search(r">=\s*(\d+)\.(\d+)", m.pyproject()["project"]["requires-python"])
    assert tuple(map(int, version.groups()[:2])) >= tuple(map(int, low.groups())), (
        f"{base} is older than requires-python {m.pyproject()['project']['requires-python']}")
    for path in m.DOCKERFILES.values():
        for ins in m.dockerfile_instructions(path):
            if ins.keyword == "FROM":
                assert ins.value.split()[0] == "${PYTHON_IMAGE}", f"{path.name}: FROM {ins.value} skips the pinned base"


@pytest.mark.parametrize("image", IMAGES)
def test_entrypoint_is_the_cli_and_cmd_parses(image):
    path = m.DOCKERFILES[image]
    final = _final(path)
    entry = m.exec_form(_one(final, "ENTRYPOINT").value)
    assert entry == ["n3dmap"] and "n3dmap" in m.pyproject()["project"]["scripts"], (
        f"{path.name}: ENTRYPOINT {entry} is not the console script pyproject installs")
    cmd = m.exec_form(_one(final, "CMD").value)
    if cmd == ["--help"]:
        return  # prints the help and exits 0: nothing more to parse
    m.parse_n3dmap(cmd, f"{path.name} CMD")


@pytest.mark.parametrize("image", IMAGES)
def test_expose_and_healthcheck_match_serve_defaults(image):
    path = m.DOCKERFILES[image]
    final = _final(path)
    http, grpc = m.cli_default(["serve"], "http_port"), m.cli_default(["serve"], "grpc_port")
    exposed = {int(p.split("/")[0]) for i in final if i.keyword == "EXPOSE" for p in i.value.split()}
    assert exposed == {http, grpc}, f"{path.name}: EXPOSE {sorted(exposed)}, `n3dmap serve` defaults to {http}/{grpc}"
    health = _one(final, "HEALTHCHECK").value
    urls = re.findall(r"http://[\w.]+:(\d+)(/\w*)", health)
    assert urls, f"{path.name}: HEALTHCHECK polls no http URL: {health}"
    for port, route in urls:
        assert int(port) == http, f"{path.name}: HEALTHCHECK polls port {port}, serve's REST default is {http}"
        assert route in rest_routes(), f"{path.name}: HEALTHCHECK polls {route}, not a route of the REST app"
    assert "N3DMAP_" not in health, f"{path.name}: the healthcheck must not depend on variables serve never reads"


REST_APP = m.ROOT / "services" / "inference" / "rest.py"


def rest_routes() -> set[str]:
    """The paths the REST app declares (`@app.get("/healthz")`, `app.mount("/x", ...)`), read from its
    source: building the real app needs a loaded model bundle."""
    import ast

    routes = set()
    for node in ast.walk(ast.parse(REST_APP.read_text())):
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                and node.func.attr in ("get", "post", "put", "delete", "api_route", "mount")
                and node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)
                and node.args[0].value.startswith("/")):
            routes.add(node.args[0].value)
    assert routes, f"found no routes in {REST_APP}: has the app moved?"
    return routes


def test_kubernetes_probe_paths_are_rest_routes():
    for path, doc in m.k8s_documents():
        for pod in m.pod_specs(path, doc):
            for c in pod.spec["containers"]:
                for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
                    get = c.get(probe, {}).get("httpGet")
                    if get and m.is_n3dmap_image(c["image"]):
                        assert get["path"] in rest_routes(), f"{pod.where}: {probe} polls {get['path']}, no such route"


# ----------------------------------------------------------------------------- environment variables

# Variables that configure programs other than n3dmap and Ray, and why they are set.
OTHER_PROGRAMS = {
    "PATH": "the venv's console scripts",
    "PYTHONUNBUFFERED": "logs reach `docker logs` / `kubectl logs` at once",
    "PIP_NO_CACHE_DIR": "smaller builder layers",
    "PIP_DISABLE_PIP_VERSION_CHECK": "quiet builds",
    "NVIDIA_VISIBLE_DEVICES": "the NVIDIA container toolkit mounts the driver",
    "NVIDIA_DRIVER_CAPABILITIES": "the NVIDIA container toolkit mounts the driver",
}


def _env_settings() -> list[tuple[str, str]]:
    """(variable, where) for every variable a Dockerfile, compose or k8s manifest sets."""
    out = []
    for path in m.DOCKERFILES.values():
        for ins in m.dockerfile_instructions(path):
            if ins.keyword == "ENV":
                out += [(name, path.name) for name in re.findall(r"(\w+)=", ins.value)]
    for name, service in m.compose()["services"].items():
        env = service.get("environment", {})
        out += [(var, f"compose service {name}") for var in (env if isinstance(env, dict) else
                                                             [e.split("=")[0] for e in env])]
    for path, doc in m.k8s_documents():
        for pod in m.pod_specs(path, doc):
            for c in pod.spec["containers"]:
                out += [(e["name"], f"{pod.where} container {c['name']}") for e in c.get("env", [])]
    return out


def _python_sources(root: Path) -> str:
    return "\n".join(p.read_text(errors="replace") for p in root.rglob("*.py"))


def _names_absent_from(names: set[str], package: Path) -> set[str]:
    """The names that appear in no .py file of `package` (stops reading once all are found)."""
    missing = set(names)
    for path in package.rglob("*.py"):
        if not missing:
            break
        text = path.read_text(errors="replace")
        missing = {name for name in missing if name not in text}
    return missing


def test_every_environment_variable_is_read_by_what_it_claims_to_configure():
    import ray

    n3dmap_code = "\n".join(_python_sources(m.ROOT / d) for d in m.pyproject_package_dirs())
    settings = _env_settings()
    assert settings
    unread_by_ray = _names_absent_from({v for v, _ in settings if v.startswith("RAY_")}, Path(ray.__file__).parent)
    for var, where in settings:
        if var.startswith("N3DMAP_"):
            assert re.search(rf"""["']{var}["']""", n3dmap_code), (
                f"{where} sets {var}, but no n3dmap code reads it: read it or drop it")
        elif var.startswith("RAY_"):
            assert var not in unread_by_ray, f"{where} sets {var}, which Ray's code never names"
        else:
            assert var in OTHER_PROGRAMS, f"{where} sets {var}: say what reads it (OTHER_PROGRAMS) or drop it"


def test_pods_run_as_the_images_user():
    uids = set()
    for path in m.DOCKERFILES.values():
        for ins in m.dockerfile_instructions(path):
            uids.update(int(u) for u in re.findall(r"useradd\b.*--uid (\d+)", ins.value))
    (uid,) = uids
    for path, doc in m.k8s_documents():
        for pod in m.pod_specs(path, doc):
            if any(m.is_n3dmap_image(c["image"]) for c in pod.spec["containers"]):
                ctx = pod.spec.get("securityContext", {})
                assert ctx.get("runAsNonRoot") and ctx.get("runAsUser") == uid, (
                    f"{pod.where}: securityContext {ctx} should be runAsNonRoot with the images' uid {uid}")
                assert ctx.get("fsGroup") == uid, f"{pod.where}: fsGroup {ctx.get('fsGroup')} != {uid}: the PVC stays unwritable"


def test_images_named_in_manifests_are_the_two_built():
    tags = {f"{m.IMAGE_REPO}:{image}" for image in m.DOCKERFILES}
    for name, service in m.compose()["services"].items():
        if m.is_n3dmap_image(service.get("image")):
            assert service["image"] in tags, f"compose {name} uses {service['image']}, built images are {tags}"
    for path, doc in m.k8s_documents():
        for pod in m.pod_specs(path, doc):
            for c in pod.spec["containers"]:
                if m.is_n3dmap_image(c["image"]):
                    assert c["image"] in tags, f"{pod.where}: image {c['image']}, built images are {tags}"
                if c["image"].startswith("eclipse/zenoh:"):
                    assert c["image"].split(":")[1] == m.pinned_requirement("eclipse-zenoh"), (
                        f"{pod.where}: zenohd {c['image']} differs from pyproject's eclipse-zenoh")
    for name, service in m.compose()["services"].items():
        if service.get("image", "").startswith("eclipse/zenoh:"):
            assert service["image"].split(":")[1] == m.pinned_requirement("eclipse-zenoh"), (
                f"compose {name}: zenohd {service['image']} differs from pyproject's eclipse-zenoh")


# ----------------------------------------------------------------------------- .dockerignore

def _dockerignore_regexes() -> list[tuple[bool, re.Pattern]]:
    """(negated, regex) per .dockerignore line, with Docker's matching: patterns are relative to the
    context root, `*` stays within a path segment, `**` spans any number of segments."""
    out = []
    for line in (m.ROOT / ".dockerignore").read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        negated = line.startswith("!")
        pattern = line.lstrip("!").strip("/")
        regex = ""
        i = 0
        while i < len(pattern):
            if pattern.startswith("**/", i):
                regex += "(?:.*/)?"
                i += 3
            elif pattern.startswith("**", i):
                regex += ".*"
                i += 2
            elif pattern[i] == "*":
                regex += "[^/]*"
                i += 1
            elif pattern[i] == "?":
                regex += "[^/]"
                i += 1
            else:
                regex += re.escape(pattern[i])
                i += 1
        out.append((negated, re.compile(regex + "(?:/.*)?")))  # a matched directory excludes its contents
    return out


def _ignored(relative: str, rules) -> bool:
    ignored = False
    for negated, regex in rules:
        if regex.fullmatch(relative):
            ignored = not negated
    return ignored


def test_dockerignore_keeps_what_the_build_copies_and_drops_local_state():
    rules = _dockerignore_regexes()
    needed = ["pyproject.toml", m.pyproject()["project"]["readme"]]
    for package in m.pyproject_package_dirs():
        needed += [p.relative_to(m.ROOT).as_posix() for p in (m.ROOT / package).rglob("*.py")]
    dropped = [p for p in needed if _ignored(p, rules)]
    assert not dropped, f".dockerignore drops files the image installs: {dropped[:5]}"
    for local in (".venv/bin/python", ".git/HEAD", "deploy/compose/volumes/data/x.tar",
                  "core/__pycache__/x.pyc", "runs/pretrain/metrics.jsonl"):
        assert _ignored(local, rules), f".dockerignore lets {local} into the build context"
