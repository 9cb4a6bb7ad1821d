"""Every command the deployment files run parses with the real CLI of the program it runs, and the
values the manifests rely on (ports, paths, modes) agree with that CLI's defaults and with each other."""

from __future__ import annotations

import shlex
from pathlib import PurePosixPath
from urllib.parse import urlsplit

import pytest

from tests.unit.deploy import manifests as m

ALL_N3DMAP = (m.compose_n3dmap_commands() + m.k8s_n3dmap_commands() + m.rayjob_entrypoints()
              + m.manifest_comment_commands())


def test_the_manifests_run_the_cli_somewhere():
    # Guards the collectors themselves: a refactor of the manifests must not make these tests vacuous.
    assert len(m.compose_n3dmap_commands()) >= 4      # inference, bridge, camera, listener
    assert len(m.k8s_n3dmap_commands()) >= 2          # inference, bridge
    assert len(m.rayjob_entrypoints()) == 1
    assert len(m.compose_ray_commands()) == 2         # ray head, ray worker


@pytest.mark.parametrize("command", ALL_N3DMAP, ids=lambda c: c.where)
def test_n3dmap_command_parses_with_the_real_parser(command):
    m.parse_n3dmap(command.argv, command.where)


def _serve_commands():
    return [c for c in m.compose_n3dmap_commands() + m.k8s_n3dmap_commands() if c.argv[:1] == ["serve"]]


def test_serve_ports_and_host_in_compose():
    defaults = {d: m.cli_default(["serve"], d) for d in ("http_port", "grpc_port")}
    for command in (c for c in _serve_commands() if c.where.startswith("compose")):
        args, _ = m.parse_n3dmap(command.argv, command.where)
        assert args.host == "0.0.0.0", f"{command.where}: serve must bind 0.0.0.0 to be reachable, binds {args.host}"
        published = {int(p.split(":")[-1]) for p in command.container.get("ports", [])}
        for dest in defaults:
            port = getattr(args, dest)
            assert port in published, f"{command.where}: serve's {dest} {port} is not among the published ports {published}"
        assert {args.http_port, args.grpc_port} == set(defaults.values()), (
            f"{command.where}: ports {args.http_port}/{args.grpc_port} differ from serve's defaults "
            f"{defaults}, which the image's EXPOSE and HEALTHCHECK use")


def test_serve_ports_probes_and_service_in_kubernetes():
    docs = m.k8s_documents()
    for path, doc in docs:
        for pod in m.pod_specs(path, doc):
            for c in pod.spec["containers"]:
                if pod.ray_node or not m.is_n3dmap_image(c.get("image")) or c["args"][:1] != ["serve"]:
                    continue
                where = f"{pod.where} container {c['name']}"
                args, _ = m.parse_n3dmap(c["args"], where)
                assert args.host == "0.0.0.0", f"{where}: serve binds {args.host}; probes and the Service need 0.0.0.0"
                ports = {p["name"]: p["containerPort"] for p in c["ports"]}
                assert set(ports.values()) == {args.http_port, args.grpc_port}, (
                    f"{where}: containerPorts {ports} are not serve's --http-port {args.http_port} / "
                    f"--grpc-port {args.grpc_port}")
                # The contract: readiness on /readyz, liveness on /healthz, both on the REST port.
                for probe, path_ in (("readinessProbe", "/readyz"), ("livenessProbe", "/healthz")):
                    get = c[probe]["httpGet"]
                    assert get["path"] == path_, f"{where}: {probe} polls {get['path']}, should poll {path_}"
                    port = ports.get(get["port"], get["port"])
                    assert port == args.http_port, f"{where}: {probe} port {get['port']} is not the REST port {args.http_port}"
                for probe in ("startupProbe",):
                    if probe in c:
                        assert ports.get(c[probe]["httpGet"]["port"], c[probe]["httpGet"]["port"]) == args.http_port
                grace = pod.spec.get("terminationGracePeriodSeconds", 30)
                assert grace > args.drain, (f"{where}: terminationGracePeriodSeconds {grace} must exceed serve's "
                                            f"--drain {args.drain}, or Kubernetes kills in-flight requests")
                _check_service_targets(docs, doc, ports, where)


def _check_service_targets(docs, deployment: dict, container_ports: dict, where: str) -> None:
    labels = deployment["spec"]["template"]["metadata"]["labels"]
    services = [d for _, d in docs if d.get("kind") == "Service"
                and d["spec"]["selector"].items() <= labels.items()]
    assert services, f"{where}: no Service selects the pods of {deployment['metadata']['name']}"
    for service in services:
        for port in service["spec"]["ports"]:
            target = port.get("targetPort", port["port"])
            assert target in container_ports or target in container_ports.values(), (
                f"Service {service['metadata']['name']} port {port['name']} targets {target!r}, "
                f"which the container does not expose ({container_ports})")


def test_hpa_targets_the_inference_deployment():
    docs = [d for _, d in m.k8s_documents()]
    deployments = {d["metadata"]["name"]: d for d in docs if d.get("kind") == "Deployment"}
    hpas = [d for d in docs if d.get("kind") == "HorizontalPodAutoscaler"]
    assert hpas, "deploy/k8s has no HorizontalPodAutoscaler"
    for hpa in hpas:
        target = hpa["spec"]["scaleTargetRef"]
        assert target["kind"] == "Deployment" and target["name"] in deployments, f"HPA targets missing {target}"
        container = deployments[target["name"]]["spec"]["template"]["spec"]["containers"][0]
        for metric in hpa["spec"]["metrics"]:
            if metric["type"] == "Resource":
                name = metric["resource"]["name"]
                assert name in container.get("resources", {}).get("requests", {}), (
                    f"HPA scales on {name} utilisation but {target['name']} requests no {name}")


def _mount_points(container: dict, kind: str) -> list[str]:
    if kind == "compose":
        return [v.split(":")[1] for v in container.get("volumes", [])]
    return [v["mountPath"] for v in container.get("volumeMounts", [])]


def _paths_in(args) -> dict[str, str]:
    """Option → value for the parsed options that name files (absolute paths)."""
    return {k: v for k, v in vars(args).items() if isinstance(v, str) and v.startswith("/")}


def _under(path: str, mounts: list[str]) -> bool:
    return any(PurePosixPath(path).is_relative_to(mount) for mount in mounts)


def test_paths_in_commands_are_on_mounted_volumes():
    for command in m.compose_n3dmap_commands():
        args, _ = m.parse_n3dmap(command.argv, command.where)
        for option, path in _paths_in(args).items():
            mounts = _mount_points(command.container, "compose")
            assert _under(path, mounts), f"{command.where}: --{option} {path} is on no mounted volume ({mounts})"
    for command in m.k8s_n3dmap_commands():
        args, _ = m.parse_n3dmap(command.argv, command.where)
        for option, path in _paths_in(args).items():
            mounts = _mount_points(command.container, "k8s")
            assert _under(path, mounts), f"{command.where}: --{option} {path} is on no mounted volume ({mounts})"


def test_rayjob_attaches_and_its_run_dir_is_shared_by_every_ray_node():
    (entry,) = m.rayjob_entrypoints()
    args, _ = m.parse_n3dmap(entry.argv, entry.where)
    assert args.attach, (f"{entry.where}: without --attach the entrypoint starts its own local Ray on the head "
                         f"pod instead of using the job's cluster")
    assert args.address is None, f"{entry.where}: the entrypoint runs on the cluster; --address would re-submit it"
    for path, doc in m.k8s_documents():
        if doc.get("kind") != "RayJob":
            continue
        cluster = doc["spec"]["rayClusterSpec"]
        assert cluster["rayVersion"] == m.pinned_requirement("ray"), "RayJob rayVersion differs from pyproject's ray"
        for pod in m.pod_specs(path, doc):
            (container,) = pod.spec["containers"]
            mounts = _mount_points(container, "k8s")
            for option in ("data", "run_dir"):
                # The run dir is Ray Train's storage_path: every node writes checkpoints there, and a
                # retried job must find them, so it has to be on the shared volume of every node.
                assert _under(getattr(args, option), mounts), (
                    f"{pod.where}: --{option.replace('_', '-')} {getattr(args, option)} is not on a volume "
                    f"mounted in this Ray node ({mounts})")
        gpus = args.workers * args.gpus_per_worker
        have = sum(g["replicas"] * float(g["template"]["spec"]["containers"][0]["resources"]["limits"]
                                         .get("nvidia.com/gpu", 0)) for g in cluster["workerGroupSpecs"])
        assert have >= gpus, f"{entry.where}: asks for {gpus} GPUs (--workers × --gpus-per-worker), cluster has {have}"


def test_ray_commands_parse_with_rays_cli_and_agree_on_ports():
    from ray._private.ray_constants import DEFAULT_PORT

    commands = {c.where.split()[-1]: c for c in m.compose_ray_commands()}
    head = m.parse_ray(commands["ray-head"].argv, commands["ray-head"].where)
    assert head["head"], "compose ray-head does not run `ray start --head`"
    assert f"{head['dashboard_port']}:{head['dashboard_port']}" in commands["ray-head"].container["ports"], (
        f"compose ray-head must publish the dashboard/Jobs port {head['dashboard_port']}")
    assert head["dashboard_host"] == "0.0.0.0", "the Ray dashboard must listen on 0.0.0.0 to be published"
    head_port = head.get("port") or DEFAULT_PORT
    worker = m.parse_ray(commands["ray-worker"].argv, commands["ray-worker"].where)
    assert worker["address"] == f"ray-head:{head_port}", f"ray-worker joins {worker['address']}, head is ray-head:{head_port}"
    check = commands["ray-head"].container["healthcheck"]["test"]
    assert check[:2] == ["CMD", "ray"], check
    status = m.parse_ray(check[2:], "compose ray-head healthcheck")
    assert status["address"].endswith(f":{head_port}")


def test_kuberay_start_params_are_ray_start_options():
    for path, doc in m.k8s_documents():
        if doc.get("kind") not in ("RayCluster", "RayJob"):
            continue
        cluster = doc["spec"].get("rayClusterSpec", doc["spec"])
        for group in [cluster["headGroupSpec"], *cluster["workerGroupSpecs"]]:
            argv = ["start"] + [f"--{k}={v}" for k, v in group["rayStartParams"].items()]
            m.parse_ray(argv, f"{path.name}: rayStartParams")
            # KubeRay writes the `ray start` command itself; a command of ours would replace the
            # images' ENTRYPOINT only with the overwrite annotation and $KUBERAY_GEN_RAY_START_CMD.
            annotations = group["template"].get("metadata", {}).get("annotations", {})
            for c in group["template"]["spec"]["containers"]:
                if "command" in c or "args" in c:
                    assert annotations.get("ray.io/overwrite-container-cmd") == "true", (
                        f"{path.name}: Ray container {c['name']} sets command/args without the "
                        f"ray.io/overwrite-container-cmd annotation; KubeRay would mangle them")


def test_submission_examples_name_paths_every_raycluster_node_mounts():
    clusters = [(p, d) for p, d in m.k8s_documents() if d.get("kind") == "RayCluster"]
    assert clusters
    for path, doc in clusters:
        examples = [c for c in m.commands_in_text(path.read_text(), path.name) if c.argv[:1] == ["train"]]
        assert examples, f"{path.name} shows no `n3dmap train --address` example"
        for command in examples:
            args, _ = m.parse_n3dmap(command.argv, command.where)
            assert args.address, f"{command.where}: a RayCluster takes jobs through --address"
            for pod in m.pod_specs(path, doc):
                (container,) = pod.spec["containers"]
                for option in ("data", "run_dir"):
                    assert _under(getattr(args, option), _mount_points(container, "k8s")), (
                        f"{command.where}: --{option.replace('_', '-')} {getattr(args, option)} is not mounted in {pod.where}")


def _zenoh_listen_ports(config_path) -> dict[str, int]:
    import json

    import zenoh

    conf = zenoh.Config.from_json5(config_path.read_text())
    endpoints = json.loads(conf.get_json("listen/endpoints"))
    return {e.split("/", 1)[0]: int(e.rsplit(":", 1)[1]) for e in endpoints}


def test_compose_stream_clients_connect_to_the_router():
    services = m.compose()["services"]
    (router_name,) = [n for n, s in services.items() if s.get("image", "").startswith("eclipse/zenoh:")]
    router = services[router_name]
    conf_arg = router["command"][router["command"].index("-c") + 1]
    (host_conf,) = [v.split(":")[0] for v in router["volumes"] if v.split(":")[1] == conf_arg]
    conf_path = (m.COMPOSE.parent / host_conf).resolve()
    assert conf_path.is_file(), f"compose {router_name} mounts {host_conf}, which does not exist"
    listen = _zenoh_listen_ports(conf_path)
    assert f"{listen['tcp']}:{listen['tcp']}" in router["ports"], f"compose {router_name} must publish {listen['tcp']}"
    streams = [c for c in m.compose_n3dmap_commands() if c.argv[0] == "stream"]
    assert {c.argv[1] for c in streams} == {"bridge", "camera", "listen"}
    for command in streams:
        args, _ = m.parse_n3dmap(command.argv, command.where)
        assert args.mode == "client", f"{command.where}: must run in client mode against the router"
        assert args.connect == [f"tcp/{router_name}:{listen['tcp']}"], (
            f"{command.where}: connects to {args.connect}, the router listens on tcp/{router_name}:{listen['tcp']}")
        assert router_name in command.container.get("depends_on", []), f"{command.where}: should depend on {router_name}"


def test_kubernetes_bridge_connects_to_the_router_service():
    docs = m.k8s_documents()
    plain = _zenoh_listen_ports(m.ROOT / "deploy" / "zenoh" / "router.json5")
    routers = [(p, d) for p, d in docs if d.get("kind") == "Deployment"
               and any(c["image"].startswith("eclipse/zenoh:") for c in d["spec"]["template"]["spec"]["containers"])]
    (router_path, router), = routers
    labels = router["spec"]["template"]["metadata"]["labels"]
    (container,) = router["spec"]["template"]["spec"]["containers"]
    container_ports = {p["name"]: p["containerPort"] for p in container["ports"]}
    for config in m.ZENOH_CONFIGS:
        for proto, port in _zenoh_listen_ports(config).items():
            assert port in container_ports.values(), f"{router_path.name}: router listens on {proto}/{port} ({config.name}) but does not expose it"
    services = [d for _, d in docs if d.get("kind") == "Service" and d["spec"]["selector"].items() <= labels.items()]
    (service,) = services
    service_ports = {p["port"]: container_ports.get(p["targetPort"], p["targetPort"]) for p in service["spec"]["ports"]}
    bridges = [c for c in m.k8s_n3dmap_commands() if c.argv[:2] == ["stream", "bridge"]]
    assert bridges, "deploy/k8s runs no stream bridge"
    for command in bridges:
        args, _ = m.parse_n3dmap(command.argv, command.where)
        assert args.mode == "client"
        for endpoint in args.connect:
            proto, address = endpoint.split("/", 1)
            host, port = address.rsplit(":", 1)
            assert host == service["metadata"]["name"], f"{command.where}: connects to {host}, the router Service is {service['metadata']['name']}"
            assert service_ports.get(int(port)) == plain[proto], (
                f"{command.where}: {endpoint} does not reach the router's {proto} listener on {plain[proto]}")


def test_submission_examples_use_the_ray_dashboard_port():
    head = m.parse_ray(["start", "--head"], "ray default")
    for command in m.manifest_comment_commands():
        args, _ = m.parse_n3dmap(command.argv, command.where)
        if getattr(args, "address", None):
            url = urlsplit(args.address)
            assert url.scheme == "http" and url.port == head["dashboard_port"], (
                f"{command.where}: --address {args.address} should be the Ray Jobs API http://HOST:{head['dashboard_port']}")


def test_comment_commands_are_real_lines():
    # shlex must see whole commands (no unbalanced quotes), and the collector must find the examples.
    commands = m.manifest_comment_commands()
    assert any(c.argv[:2] == ["train", "pretrain"] for c in commands), [c.where for c in commands]
    for c in commands:
        assert shlex.join(c.argv)
