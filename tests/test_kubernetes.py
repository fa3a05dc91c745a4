"""The Kubernetes manifests (deploy/kubernetes/) against Kubernetes 1.33's schemas, offline, and
against the service they deploy.

* every manifest validates (kubernetes-validate, its bundled schemas, strict: no unknown
  field), with the network shut; a broken copy is rejected (the check can fail);
* kustomize's files list every manifest and nothing missing;
* the ConfigMap's and the Deployment's ``PLANNER_*`` names are settings that
  service/settings.py reads, and their values pass its validation;
* the probes' paths and the Ingress's paths are routes of the app; the ports, selectors and
  names agree; the grace period exceeds the drain time; the writable paths are volumes.
"""

from __future__ import annotations

import copy
import re
import socket
from pathlib import Path
from typing import Any

import pytest
import yaml

import kubernetes_validate  # in the test extra: its absence must fail, not skip

from service.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
KDIR = ROOT / "deploy" / "kubernetes"
#: The Kubernetes version whose schemas the manifests must satisfy.
K8S_VERSION = "1.33"
KUSTOMIZE_KINDS = {"Kustomization", "Component"}


def _docs(path: Path) -> list[dict[str, Any]]:
    return [d for d in yaml.safe_load_all(path.read_text()) if d]


def _manifests() -> list[tuple[Path, dict[str, Any]]]:
    out = []
    for p in sorted(KDIR.rglob("*.yaml")):
        for d in _docs(p):
            if d.get("kind") not in KUSTOMIZE_KINDS:
                out.append((p, d))
    return out


def _one(kind: str) -> dict[str, Any]:
    found = [d for _, d in _manifests() if d["kind"] == kind]
    assert len(found) == 1, kind
    return found[0]


@pytest.fixture()
def no_network(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*args: Any, **kwargs: Any) -> None:
        raise OSError("network access during an offline test")
    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)


def test_every_manifest_validates_offline(no_network: None) -> None:
    manifests = _manifests()
    kinds = sorted(d["kind"] for _, d in manifests)
    assert kinds == ["ConfigMap", "Deployment", "HorizontalPodAutoscaler", "Ingress",
                     "PodDisruptionBudget", "Secret", "Service"]
    for path, doc in manifests:
        version = kubernetes_validate.validate(doc, K8S_VERSION, strict=True)
        assert version == K8S_VERSION, (path, version)


@pytest.mark.parametrize("path, value", [
    (("spec", "replicas"), "two"),
    (("spec", "template", "spec", "containers", 0, "readinessProbes"), {}),  # a typo
    (("spec", "template", "spec", "containers", 0, "readinessProbe", "httpGet", "path"), 5),
])
def test_a_broken_manifest_is_rejected(no_network: None, path: tuple[Any, ...],
                                       value: Any) -> None:
    doc = copy.deepcopy(_one("Deployment"))
    node = doc
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(doc, K8S_VERSION, strict=True)


def test_kustomization_lists_every_manifest() -> None:
    kust = _docs(KDIR / "kustomization.yaml")[0]
    listed = {KDIR / r for r in kust["resources"]}
    assert all(p.exists() for p in listed), listed
    comp = _docs(KDIR / "ingress" / "kustomization.yaml")[0]
    assert comp["kind"] == "Component"
    in_component = {KDIR / "ingress" / r for r in comp["resources"]}
    assert all(p.exists() for p in in_component)
    # the Secret is an example (the keys must be the operator's own); nothing else is left out
    files = {p for p in KDIR.rglob("*.yaml") if p.name != "kustomization.yaml"}
    assert files - listed - in_component == {KDIR / "secret.example.yaml"}
    assert "#   - ingress" in (KDIR / "kustomization.yaml").read_text()
    assert kust["images"][0]["name"] == _one("Deployment")["spec"]["template"]["spec"][
        "containers"][0]["image"]


def _setting_names() -> set[str]:
    return {f"PLANNER_{name.upper()}" for name in Settings.model_fields}


def test_configured_names_are_settings_and_their_values_valid(
        monkeypatch: pytest.MonkeyPatch) -> None:
    data = _one("ConfigMap")["data"]
    names = _setting_names()
    unknown = sorted(set(data) - names)
    assert not unknown, f"the service reads no setting {unknown}"
    pod = _one("Deployment")["spec"]["template"]["spec"]
    container = pod["containers"][0]
    assert container["envFrom"][0]["configMapRef"]["name"] == _one("ConfigMap")["metadata"]["name"]
    env = {e["name"]: e for e in container["env"]}
    assert {k for k in env if k.startswith("PLANNER_")} <= names
    secret = env["PLANNER_API_KEYS"]["valueFrom"]["secretKeyRef"]
    example = _one("Secret")
    assert secret["name"] == example["metadata"]["name"]
    assert secret["key"] in example["stringData"]
    # the values pass the service's own validation (from the environment, as in the pod)
    for k in list(__import__("os").environ):
        if k.startswith("PLANNER_"):
            monkeypatch.delenv(k)
    for k, v in data.items():
        monkeypatch.setenv(k, v)
    monkeypatch.setenv("PLANNER_API_KEYS", example["stringData"]["PLANNER_API_KEYS"])
    s = Settings()
    assert s.workers == int(data["PLANNER_WORKERS"])
    assert len(s.api_keys) == 2
    assert s.native_cache_dir == data["PLANNER_NATIVE_CACHE"]


def test_probes_and_ingress_paths_are_routes_of_the_app() -> None:
    from service.main import create_app
    from service.settings import default_settings

    app = create_app(default_settings())
    spec = app.openapi()
    container = _one("Deployment")["spec"]["template"]["spec"]["containers"][0]
    assert container["readinessProbe"]["httpGet"]["path"] == "/readyz"
    assert container["livenessProbe"]["httpGet"]["path"] == "/healthz"
    for probe in ("readinessProbe", "livenessProbe", "startupProbe"):
        path = container[probe]["httpGet"]["path"]
        assert "get" in spec["paths"][path], path
    # every Ingress path reaches some route; /metrics is not exposed
    routes = set(spec["paths"]) | {"/docs", "/redoc", "/openapi.json", "/static", "/"}
    ingress_paths = [p for rule in _one("Ingress")["spec"]["rules"]
                     for p in rule["http"]["paths"]]
    for p in ingress_paths:
        if p["pathType"] == "Exact":
            assert p["path"] in routes, p
        else:
            assert any(r == p["path"] or r.startswith(p["path"] + "/") for r in routes), p
    assert not any(p["path"] in ("/metrics", "/") and p["pathType"] == "Prefix"
                   for p in ingress_paths)


def test_ports_selectors_and_names_agree() -> None:
    dep = _one("Deployment")
    pod = dep["spec"]["template"]
    labels = pod["metadata"]["labels"]
    container = pod["spec"]["containers"][0]
    port = container["ports"][0]
    assert port["containerPort"] == int(_one("ConfigMap")["data"]["PLANNER_PORT"])
    for probe in ("readinessProbe", "livenessProbe", "startupProbe"):
        assert container[probe]["httpGet"]["port"] == port["name"]
    svc = _one("Service")
    assert svc["spec"]["ports"][0]["targetPort"] == port["name"]
    for selector in (svc["spec"]["selector"], dep["spec"]["selector"]["matchLabels"],
                     _one("PodDisruptionBudget")["spec"]["selector"]["matchLabels"]):
        assert selector.items() <= labels.items()
    target = _one("HorizontalPodAutoscaler")["spec"]["scaleTargetRef"]
    assert (target["kind"], target["name"]) == ("Deployment", dep["metadata"]["name"])
    backend = _one("Ingress")["spec"]["rules"][0]["http"]["paths"][0]["backend"]["service"]
    assert backend["name"] == svc["metadata"]["name"]
    assert backend["port"]["name"] == svc["spec"]["ports"][0]["name"]
    hpa = _one("HorizontalPodAutoscaler")["spec"]
    assert hpa["metrics"][0]["resource"]["name"] == "cpu"
    assert _one("PodDisruptionBudget")["spec"]["minAvailable"] < hpa["minReplicas"]


def _cpus(q: str) -> float:
    return float(q[:-1]) / 1000 if q.endswith("m") else float(q)


def test_grace_resources_and_writable_paths() -> None:
    data = _one("ConfigMap")["data"]
    pod = _one("Deployment")["spec"]["template"]["spec"]
    container = pod["containers"][0]
    pause = int(container["lifecycle"]["preStop"]["exec"]["command"][-1])
    assert pod["terminationGracePeriodSeconds"] > float(data["PLANNER_SHUTDOWN_TIMEOUT"]) + pause
    # one solver worker per CPU of the limit; the request covers them (the HPA's base)
    assert int(data["PLANNER_WORKERS"]) <= _cpus(container["resources"]["limits"]["cpu"])
    assert _cpus(container["resources"]["requests"]["cpu"]) >= int(data["PLANNER_WORKERS"])
    # non-root, the Dockerfile's user, read-only root: every written path is an emptyDir
    uid = re.search(r"useradd .*--uid (\d+)", (ROOT / "Dockerfile").read_text())
    assert uid and pod["securityContext"]["runAsUser"] == int(uid.group(1))
    assert pod["securityContext"]["runAsNonRoot"] is True
    empty = {v["name"] for v in pod["volumes"] if "emptyDir" in v}
    for c in pod["containers"] + pod["initContainers"]:
        assert c["securityContext"]["readOnlyRootFilesystem"] is True
        assert c["securityContext"]["allowPrivilegeEscalation"] is False
        assert {m["name"] for m in c["volumeMounts"]} <= empty
    mounts = [m["mountPath"] for m in container["volumeMounts"]]
    assert "/tmp" in mounts
    cache = data["PLANNER_NATIVE_CACHE"]
    # a subdirectory of a mount: optimizer.native refuses a directory others may write, and an
    # emptyDir's root is world-writable
    assert any(cache.startswith(m.rstrip("/") + "/") for m in mounts), cache
    env = {e["name"]: e.get("value") for e in container["env"]}
    assert env["MPLCONFIGDIR"].startswith("/tmp/")
