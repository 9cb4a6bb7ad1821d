"""Readers for the deployment files (docker/, deploy/, .dockerignore, README) and the real CLIs they
call, shared by the tests in this directory. No Docker engine, no cluster: the files are parsed and
every command in them is parsed by the real argument parser of the program it runs."""

from __future__ import annotations

import contextlib
import functools
import io
import json
import re
import shlex
import tomllib
from dataclasses import dataclass
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[3]
DOCKERFILES = {"cpu": ROOT / "docker" / "Dockerfile.cpu", "cuda": ROOT / "docker" / "Dockerfile.cuda"}
COMPOSE = ROOT / "deploy" / "compose" / "compose.yaml"
K8S_DIR = ROOT / "deploy" / "k8s"
ZENOH_CONFIGS = sorted((ROOT / "deploy" / "zenoh").glob("*.json5"))
IMAGE_REPO = "n3dmap"          # the images' repository name in every manifest (n3dmap:cpu, n3dmap:cuda)


# ----------------------------------------------------------------------------- YAML

def load_yaml_documents(path: Path) -> list[dict]:
    with path.open() as f:
        return [doc for doc in yaml.safe_load_all(f) if doc is not None]


def k8s_documents() -> list[tuple[Path, dict]]:
    """(file, document) for every document of every deploy/k8s/*.yaml."""
    return [(path, doc) for path in sorted(K8S_DIR.glob("*.yaml")) for doc in load_yaml_documents(path)]


def compose() -> dict:
    (doc,) = load_yaml_documents(COMPOSE)
    return doc


def is_n3dmap_image(image: str | None) -> bool:
    return bool(image) and image.rsplit("/", 1)[-1].split(":")[0] == IMAGE_REPO


@dataclass(frozen=True)
class PodSpecRef:
    """A pod template found in a k8s document, with where it is (for messages)."""

    where: str
    spec: dict
    ray_node: bool            # a KubeRay head/worker: KubeRay writes the container command


def pod_specs(path: Path, doc: dict) -> list[PodSpecRef]:
    kind, name = doc.get("kind"), doc.get("metadata", {}).get("name")
    where = f"{path.name}: {kind} {name}"
    spec = doc.get("spec", {})
    if kind in ("Deployment", "StatefulSet", "DaemonSet", "Job"):
        return [PodSpecRef(where, spec["template"]["spec"], False)]
    cluster = spec.get("rayClusterSpec") if kind == "RayJob" else spec if kind == "RayCluster" else None
    if cluster is None:
        return []
    groups = [("head", cluster["headGroupSpec"])] + [(g["groupName"], g) for g in cluster.get("workerGroupSpecs", [])]
    return [PodSpecRef(f"{where} ({group})", g["template"]["spec"], True) for group, g in groups]


# ----------------------------------------------------------------------------- the n3dmap CLI

@functools.lru_cache(maxsize=1)
def n3dmap_parser():
    from services.cli.main import build_parser

    return build_parser(full=True)


def _subparser_choices(parser) -> dict:
    for action in parser._actions:  # argparse has no public accessor for its subparsers
        if action.__class__.__name__ == "_SubParsersAction":
            return action.choices
    return {}


def leaf_parser(argv: list[str]):
    """The (sub)parser that handles the options of `n3dmap <argv>`: follow the leading subcommands."""
    parser = n3dmap_parser()
    for token in argv:
        choices = _subparser_choices(parser)
        if token.startswith("-") or token not in choices:
            break
        parser = choices[token]
    return parser


def parse_n3dmap(argv: list[str], where: str):
    """Parse `n3dmap <argv>` with the real parser; assert it parses and that every option is spelled
    in full (argparse would accept an abbreviation, which breaks when a longer option is added).
    Returns (namespace, leaf parser)."""
    leaf = leaf_parser(argv)
    for token in argv:
        if token.startswith("--"):
            option = token.split("=", 1)[0]
            assert option in leaf._option_string_actions, (
                f"{where}: `n3dmap {shlex.join(argv)}` uses {option}, which `{leaf.prog}` does not have "
                f"(its options: {sorted(o for o in leaf._option_string_actions if o.startswith('--'))})")
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            namespace = n3dmap_parser().parse_args(argv)
    except SystemExit as e:
        raise AssertionError(f"{where}: `n3dmap {shlex.join(argv)}` does not parse "
                             f"(exit {e.code}): {err.getvalue().strip()}") from None
    return namespace, leaf


def cli_default(argv_prefix: list[str], dest: str):
    """The default the real parser gives option `dest` of the subcommand `argv_prefix`."""
    return leaf_parser(argv_prefix).get_default(dest)


# ----------------------------------------------------------------------------- the ray CLI

def parse_ray(argv: list[str], where: str) -> dict:
    """Parse `ray <argv>` with Ray's own click CLI; returns its parameters."""
    import warnings

    import click

    with warnings.catch_warnings():  # importing ray's CLI imports ray.serve, which warns about pydantic
        warnings.simplefilter("ignore")
        from ray.scripts.scripts import cli

    command = cli.get_command(None, argv[0])
    assert command is not None, f"{where}: `ray {argv[0]}` is not a ray command"
    try:
        return command.make_context(argv[0], list(argv[1:])).params
    except click.UsageError as e:
        raise AssertionError(f"{where}: `ray {shlex.join(argv)}` does not parse: {e.format_message()}") from None


# ----------------------------------------------------------------------------- where commands are

@dataclass(frozen=True)
class Command:
    where: str
    argv: list[str]          # without the program name
    container: dict | None   # the compose service or k8s container that runs it (None: docs)


def compose_n3dmap_commands() -> list[Command]:
    """Compose services running the n3dmap image's ENTRYPOINT (`n3dmap`) with their `command:`."""
    out = []
    for name, service in compose()["services"].items():
        if is_n3dmap_image(service.get("image")) and "entrypoint" not in service:
            out.append(Command(f"compose service {name}", list(service["command"]), service))
    return out


def compose_ray_commands() -> list[Command]:
    out = []
    for name, service in compose()["services"].items():
        if service.get("entrypoint") == ["ray"]:
            out.append(Command(f"compose service {name}", list(service["command"]), service))
    return out


def k8s_n3dmap_commands() -> list[Command]:
    """Containers of the n3dmap images whose command is the image's ENTRYPOINT, with their `args:`."""
    out = []
    for path, doc in k8s_documents():
        for pod in pod_specs(path, doc):
            if pod.ray_node:
                continue
            for c in pod.spec["containers"]:
                if is_n3dmap_image(c.get("image")):
                    assert "command" not in c, f"{pod.where}: container {c['name']} overrides the n3dmap ENTRYPOINT"
                    out.append(Command(f"{pod.where} container {c['name']}", list(c["args"]), c))
    return out


def rayjob_entrypoints() -> list[Command]:
    out = []
    for path, doc in k8s_documents():
        if doc.get("kind") == "RayJob":
            argv = shlex.split(doc["spec"]["entrypoint"])
            assert argv[0] == "n3dmap", f"{path.name}: RayJob entrypoint should run the n3dmap CLI, got {argv[0]!r}"
            out.append(Command(f"{path.name}: RayJob {doc['metadata']['name']} entrypoint", argv[1:], None))
    return out


# An example command: a line of its own, or an indented comment line (`#   n3dmap ...`), not prose.
_DOC_COMMAND = re.compile(r"^\s*(?:(?:#|//)\s{2,})?(n3dmap\s.*)$")


def commands_in_text(text: str, where: str) -> list[Command]:
    """`n3dmap ...` lines of a text (shell comments and README code blocks), with `\\` continuations."""
    joined = re.sub(r"\\\n\s*(?:(?:#|//)\s*)?", " ", text)
    out = []
    for lineno, line in enumerate(joined.splitlines(), 1):
        m = _DOC_COMMAND.match(line)
        if not m:
            continue
        command = m.group(1).split(" #", 1)[0].split(" &", 1)[0].strip()
        argv = shlex.split(command)[1:]
        out.append(Command(f"{where} (`{command}`)", argv, None))
    return out


def manifest_comment_commands() -> list[Command]:
    files = [COMPOSE, *sorted(K8S_DIR.glob("*.yaml")), *DOCKERFILES.values(), *ZENOH_CONFIGS]
    return [c for path in files for c in commands_in_text(path.read_text(), path.relative_to(ROOT).as_posix())]


# ----------------------------------------------------------------------------- Dockerfiles

@dataclass(frozen=True)
class Instruction:
    keyword: str
    value: str
    stage: int               # index of the FROM stage it belongs to (-1: before the first FROM)


def dockerfile_instructions(path: Path) -> list[Instruction]:
    """The instructions of a Dockerfile, continuation lines joined, comments dropped."""
    lines, buffer = [], ""
    for raw in path.read_text().splitlines():
        stripped = raw.strip()
        if not buffer and (not stripped or stripped.startswith("#")):
            continue
        if buffer and stripped.startswith("#"):
            continue
        if stripped.endswith("\\"):
            buffer += stripped[:-1] + " "
            continue
        lines.append(buffer + stripped)
        buffer = ""
    out, stage = [], -1
    for line in lines:
        keyword, _, value = line.partition(" ")
        keyword = keyword.upper()
        if keyword == "FROM":
            stage += 1
        out.append(Instruction(keyword, value.strip(), stage))
    return out


def exec_form(value: str) -> list[str]:
    """A JSON-array instruction argument (CMD/ENTRYPOINT/HEALTHCHECK ... CMD [...])."""
    parsed = json.loads(value)
    assert isinstance(parsed, list) and all(isinstance(x, str) for x in parsed), value
    return parsed


def dockerfile_args(path: Path) -> dict[str, str]:
    """ARG defaults (global and per stage; a name keeps its first default)."""
    out: dict[str, str] = {}
    for ins in dockerfile_instructions(path):
        if ins.keyword == "ARG" and "=" in ins.value:
            name, default = ins.value.split("=", 1)
            out.setdefault(name.strip(), default.strip().strip('"'))
    return out


def expand_args(text: str, args: dict[str, str]) -> str:
    return re.sub(r"\$\{(\w+)\}|\$(\w+)", lambda m: args.get(m.group(1) or m.group(2), m.group(0)), text)


# ----------------------------------------------------------------------------- pyproject

@functools.lru_cache(maxsize=1)
def pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def pyproject_package_dirs() -> list[str]:
    """Top-level directories holding the packages `[tool.setuptools.packages.find]` includes."""
    import fnmatch

    patterns = pyproject()["tool"]["setuptools"]["packages"]["find"]["include"]
    dirs = [p.name for p in ROOT.iterdir() if p.is_dir() and (p / "__init__.py").is_file()]
    return sorted(d for d in dirs if any(fnmatch.fnmatchcase(d, pat) for pat in patterns))


def pinned_requirement(name: str) -> str:
    """The exact version pyproject pins `name` to (`name==X`)."""
    for req in pyproject()["project"]["dependencies"]:
        m = re.fullmatch(rf"{re.escape(name)}(?:\[[^\]]*\])?\s*==\s*([\w.]+)", req.strip())
        if m:
            return m.group(1)
    raise AssertionError(f"pyproject.toml does not pin {name} with ==")
