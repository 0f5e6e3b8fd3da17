#!/usr/bin/env python3
"""Offline, deterministic consistency checks for the files under deploy/ (run by deploy/validate.sh).

Each sub-command checks one group of files, prints one line per thing it checked, and exits non-zero when
anything is wrong. Schema validation of the Kubernetes objects is done by kubernetes-validate in
validate.sh; this script checks what a schema cannot: that the files agree with each other and with the
server (config keys from alignment-server/src/config.rs, metric names from alignment-server/src/metrics.rs).

Needs Python >= 3.11 (tomllib), PyYAML and promql-parser (deploy/requirements-validate.txt).
"""

from __future__ import annotations

import ipaddress
import json
import re
import sys
import tomllib
from pathlib import Path

import promql_parser
import yaml

DEPLOY = Path(__file__).resolve().parent
ROOT = DEPLOY.parent
K8S = DEPLOY / "k8s"
CONFIG_RS = ROOT / "alignment-server" / "src" / "config.rs"
METRICS_RS = ROOT / "alignment-server" / "src" / "metrics.rs"

# Files in deploy/k8s/ that are deliberately not in kustomization.yaml.
K8S_NOT_IN_KUSTOMIZATION = {"kustomization.yaml", "secret.example.yaml", "prometheus-adapter-rules.yaml"}


class Checker:
    def __init__(self, group: str) -> None:
        self.group = group
        self.errors: list[str] = []

    def ok(self, what: str) -> None:
        print(f"  ok    {self.group}: {what}")

    def fail(self, what: str) -> None:
        print(f"  FAIL  {self.group}: {what}")
        self.errors.append(what)

    def check(self, cond: bool, what: str, why: str = "") -> bool:
        if cond:
            self.ok(what)
        else:
            self.fail(f"{what}{' (' + why + ')' if why else ''}")
        return cond

    def done(self) -> int:
        return 1 if self.errors else 0


def rel(p: Path) -> str:
    try:
        return str(p.relative_to(ROOT))
    except ValueError:
        return str(p)


def load_yaml_docs(path: Path) -> list:
    with path.open() as f:
        return [d for d in yaml.safe_load_all(f) if d is not None]


def parse_promql(expr: str) -> str | None:
    """None when `expr` parses, else the parser's message."""
    try:
        promql_parser.parse(expr)
    except Exception as e:  # noqa: BLE001 - the parser raises ValueError, be liberal
        return str(e)
    return None


# ---- the server's own definitions ----------------------------------------------------------------------

def config_schema() -> dict[str, set[str]] | None:
    """TOML sections and keys accepted by the server, read from the clap/serde structs in config.rs."""
    if not CONFIG_RS.is_file():
        return None
    src = CONFIG_RS.read_text()
    sections = {
        "QuicConfig": "quic", "AuthConfig": "auth", "LimitsConfig": "limits", "BatchConfig": "batch",
        "EngineConfig": "engine", "RefineConfig": "refine", "InternalConfig": "internal", "LogConfig": "log",
    }
    schema: dict[str, set[str]] = {}
    for struct, section in sections.items():
        m = re.search(r"pub struct " + struct + r" \{(.*?)\n\}", src, re.S)
        if not m:
            return None
        schema[section] = set(re.findall(r"pub (\w+): Option<", m.group(1)))
    return schema


def server_metric_names() -> set[str] | None:
    if not METRICS_RS.is_file():
        return None
    # Every holoface_* identifier in the file: the exported names (HELP/TYPE lines, format strings) and a
    # few harmless extras (the crate name holoface_protocol, test expectations).
    return set(re.findall(r"\bholoface_[a-z_]*[a-z]", METRICS_RS.read_text()))


def is_internal_ip(host: str) -> bool:
    """Mirror of holoface_alignment_server::metrics_http::is_internal_addr."""
    ip = ipaddress.ip_address(host.strip("[]"))
    if ip.version == 4:
        nets = ["127.0.0.0/8", "10.0.0.0/8", "172.16.0.0/12", "192.168.0.0/16", "169.254.0.0/16"]
    else:
        nets = ["::1/128", "fc00::/7", "fe80::/10"]
    return any(ip in ipaddress.ip_network(n) for n in nets)


def split_hostport(addr: str) -> tuple[str, int]:
    host, _, port = addr.rpartition(":")
    return host, int(port)


# ---- TOML configuration files --------------------------------------------------------------------------

def check_toml() -> int:
    c = Checker("toml")
    schema = config_schema()
    if schema is None:
        print(f"  skip  toml: key check ({rel(CONFIG_RS)} not found or not understood)")
    files = [DEPLOY / "server.container.toml", DEPLOY / "systemd" / "server.toml", DEPLOY / "server.example.toml"]
    for path in files:
        try:
            cfg = tomllib.loads(path.read_text())
        except (OSError, tomllib.TOMLDecodeError) as e:
            c.fail(f"{rel(path)} parses as TOML ({e})")
            continue
        c.ok(f"{rel(path)} parses as TOML")
        if schema is not None:
            unknown = [f"[{s}]" for s in cfg if s not in schema]
            unknown += [f"{s}.{k}" for s, kv in cfg.items() if s in schema and isinstance(kv, dict)
                        for k in kv if k not in schema[s]]
            c.check(not unknown, f"{rel(path)}: every key is one the server knows", f"unknown: {unknown}")
        listen = cfg.get("internal", {}).get("metrics_listen")
        if listen is not None:
            host, _ = split_hostport(listen)
            c.check(is_internal_ip(host), f"{rel(path)}: internal.metrics_listen {listen} is loopback/private",
                    "the server refuses any other address, 0.0.0.0 included")
        if path.name != "server.example.toml":
            auth = cfg.get("auth", {})
            c.check("tokens" not in auth and auth.get("tokens_file"),
                    f"{rel(path)}: tokens come from a file, not from the config", "set auth.tokens_file only")
            c.check(auth.get("allow_anonymous") is False, f"{rel(path)}: allow_anonymous = false")
            q = cfg.get("quic", {})
            c.check(bool(q.get("cert")) and bool(q.get("key")), f"{rel(path)}: quic.cert and quic.key are set",
                    "without them every start generates a new self-signed certificate")
    return c.done()


# ---- Kubernetes manifests ------------------------------------------------------------------------------

def k8s_objects() -> dict[str, list[dict]]:
    return {p.name: load_yaml_docs(p) for p in sorted(K8S.glob("*.yaml"))}


def find(objs: dict[str, list[dict]], kind: str) -> list[dict]:
    return [o for docs in objs.values() for o in docs if isinstance(o, dict) and o.get("kind") == kind]


def check_k8s() -> int:
    c = Checker("k8s")
    objs = k8s_objects()
    kust = objs.get("kustomization.yaml", [{}])[0]
    listed = kust.get("resources", [])
    c.check(all((K8S / r).is_file() for r in listed), "kustomization.yaml: every listed resource exists")
    unlisted = sorted(set(objs) - set(listed) - K8S_NOT_IN_KUSTOMIZATION)
    c.check(not unlisted, "kustomization.yaml lists every manifest (except the secret template and adapter rules)",
            f"not listed: {unlisted}")
    c.check("namespace" not in kust and not any(
        o.get("metadata", {}).get("namespace") for n, docs in objs.items() if n != "prometheus-adapter-rules.yaml"
        for o in docs if isinstance(o, dict)), "manifests are namespace-agnostic")

    deps = find(objs, "Deployment")
    if not c.check(len(deps) == 1, "exactly one Deployment"):
        return c.done()
    dep = deps[0]
    name = dep["metadata"]["name"]
    spec = dep["spec"]
    pod = spec["template"]
    pod_labels = pod["metadata"].get("labels", {})

    def selects(sel: dict) -> bool:
        return bool(sel) and all(pod_labels.get(k) == v for k, v in sel.items())

    c.check(selects(spec["selector"]["matchLabels"]), "Deployment selector matches its pod labels")
    ctr = pod["spec"]["containers"][0]
    ports = {p["name"]: p for p in ctr.get("ports", [])}

    # Image name is the one kustomization.yaml rewrites.
    images = [i["name"] for i in kust.get("images", [])]
    c.check(ctr["image"].split(":")[0] in images, f"container image '{ctr['image']}' is rewritten by kustomization images")

    # Services.
    for svc in find(objs, "Service"):
        sname = svc["metadata"]["name"]
        c.check(selects(svc["spec"].get("selector", {})), f"Service {sname} selects the Deployment's pods")
        for sp in svc["spec"]["ports"]:
            tp = ports.get(sp["targetPort"]) if isinstance(sp["targetPort"], str) else None
            c.check(tp is not None and tp.get("protocol", "TCP") == sp.get("protocol", "TCP"),
                    f"Service {sname} port {sp['name']} -> container port '{sp['targetPort']}' ({sp.get('protocol', 'TCP')})")
    quic = [s for s in find(objs, "Service") if any(p.get("protocol") == "UDP" for p in s["spec"]["ports"])]
    c.check(len(quic) == 1 and quic[0]["spec"].get("sessionAffinity") == "ClientIP",
            "the UDP (QUIC) Service has sessionAffinity: ClientIP")
    c.check(len(quic) == 1 and quic[0]["spec"].get("externalTrafficPolicy") == "Local",
            "the UDP Service keeps client source addresses (externalTrafficPolicy: Local)")

    # Probes and the metrics listener.
    for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
        hg = ctr.get(probe, {}).get("httpGet", {})
        c.check(hg.get("path") == "/health" and hg.get("port") in ports, f"{probe} is GET /health on a named container port")
    env = {e["name"]: e for e in ctr.get("env", [])}
    metrics_port = ports.get("metrics", {}).get("containerPort")
    ml = env.get("HOLOFACE_METRICS_LISTEN", {}).get("value", "")
    c.check(ml.endswith(f":{metrics_port}") and "$(POD_IP)" in ml and "POD_IP" in env,
            "HOLOFACE_METRICS_LISTEN binds the pod IP on the metrics port")
    ann = pod["metadata"].get("annotations", {})
    c.check(ann.get("prometheus.io/scrape") == "true" and ann.get("prometheus.io/port") == str(metrics_port)
            and ann.get("prometheus.io/path") == "/metrics", "Prometheus scrape annotations point at /metrics on the metrics port")

    # Security context.
    sc, psc = ctr.get("securityContext", {}), pod["spec"].get("securityContext", {})
    c.check(psc.get("runAsNonRoot") is True and sc.get("readOnlyRootFilesystem") is True
            and sc.get("allowPrivilegeEscalation") is False and sc.get("capabilities", {}).get("drop") == ["ALL"],
            "non-root, read-only root filesystem, no privilege escalation, all capabilities dropped")
    res = ctr.get("resources", {})
    c.check(all(res.get(k, {}).get(r) for k in ("requests", "limits") for r in ("cpu", "memory")),
            "CPU and memory requests and limits are set")

    # Volumes: config map and secrets exist / are referenced consistently.
    vols = {v["name"]: v for v in pod["spec"].get("volumes", [])}
    c.check(all(m["name"] in vols for m in ctr.get("volumeMounts", [])), "every volumeMount has a volume")
    cms = {o["metadata"]["name"]: o for o in find(objs, "ConfigMap")}
    cm_refs = [v["configMap"]["name"] for v in vols.values() if "configMap" in v]
    c.check(all(r in cms for r in cm_refs), f"ConfigMap(s) {cm_refs} are defined")
    secret_refs = sorted(s["secret"]["name"] for v in vols.values() if "projected" in v for s in v["projected"]["sources"])
    template = sorted(o["metadata"]["name"] for o in load_yaml_docs(K8S / "secret.example.yaml"))
    c.check(secret_refs == template, f"Secrets mounted {secret_refs} match the template secret.example.yaml")

    # The ConfigMap carries exactly the image's config.
    container_toml = (DEPLOY / "server.container.toml").read_text()
    cm_toml = next(iter(cms.values()))["data"].get("server.toml", "") if cms else ""
    c.check(cm_toml == container_toml, "configmap.yaml server.toml is identical to deploy/server.container.toml")
    cfg = tomllib.loads(container_toml)
    check_asset_paths(c, cfg, "server.container.toml")
    mount_paths = {m["mountPath"] for m in ctr.get("volumeMounts", [])}
    c.check("/etc/holoface/server.toml" in mount_paths, "the ConfigMap is mounted where the entrypoint reads it")
    secret_dir = next((m["mountPath"] for m in ctr.get("volumeMounts", []) if vols[m["name"]].get("projected")), "")
    needed = [cfg["quic"]["cert"], cfg["quic"]["key"], cfg["auth"]["tokens_file"]]
    items = {f"{secret_dir}/{i['path']}" for v in vols.values() if "projected" in v
             for s in v["projected"]["sources"] for i in s["secret"].get("items", [])}
    c.check(all(p in items for p in needed), f"cert, key and tokens_file paths {needed} are provided by the secret volume")

    # Shutdown timing.
    shutdown_s = cfg["limits"]["shutdown_timeout_ms"] / 1000
    pre = ctr.get("lifecycle", {}).get("preStop", {}).get("exec", {}).get("command", [])
    pre_s = float(pre[-1]) if pre and pre[0].endswith("sleep") else 0.0
    grace = pod["spec"].get("terminationGracePeriodSeconds", 30)
    c.check(grace > pre_s + shutdown_s, f"terminationGracePeriodSeconds {grace} > preStop {pre_s:g} s + shutdown timeout {shutdown_s:g} s")

    # HPA and PDB.
    hpas = find(objs, "HorizontalPodAutoscaler")
    if c.check(len(hpas) == 1, "one HorizontalPodAutoscaler"):
        hpa = hpas[0]["spec"]
        c.check(hpa["scaleTargetRef"]["kind"] == "Deployment" and hpa["scaleTargetRef"]["name"] == name,
                "HPA targets the Deployment")
        pod_metrics = [m["pods"]["metric"]["name"] for m in hpa["metrics"] if m["type"] == "Pods"]
        adapter = load_yaml_docs(K8S / "prometheus-adapter-rules.yaml")[0]
        served = [r["name"]["as"] for r in adapter.get("rules", [])]
        c.check(bool(pod_metrics) and all(m in served for m in pod_metrics),
                f"HPA Pods metric(s) {pod_metrics} are served by prometheus-adapter-rules.yaml")
        c.check(any(m["type"] == "Resource" and m["resource"]["name"] == "cpu" for m in hpa["metrics"]),
                "HPA also scales on CPU")
        pdbs = find(objs, "PodDisruptionBudget")
        c.check(len(pdbs) == 1 and selects(pdbs[0]["spec"]["selector"]["matchLabels"]), "PDB selects the Deployment's pods")
        if pdbs:
            c.check(hpa["minReplicas"] >= 2 or "maxUnavailable" not in pdbs[0]["spec"],
                    "HPA minReplicas >= 2, so the PDB never blocks every drain")
    return c.done()


# ---- prometheus-adapter rules --------------------------------------------------------------------------

def check_adapter() -> int:
    c = Checker("adapter")
    path = K8S / "prometheus-adapter-rules.yaml"
    doc = load_yaml_docs(path)[0]
    rules = doc.get("rules")
    if not c.check(isinstance(rules, list) and rules, f"{rel(path)} has a non-empty rules list"):
        return c.done()
    for r in rules:
        name = r.get("name", {}).get("as", "?")
        err = parse_promql(r.get("seriesQuery", ""))
        c.check(err is None, f"rule {name}: seriesQuery is valid PromQL", err or "")
        ov = r.get("resources", {}).get("overrides", {})
        c.check(ov.get("namespace", {}).get("resource") == "namespace" and ov.get("pod", {}).get("resource") == "pod",
                f"rule {name}: maps the namespace and pod labels to resources")
        mq = r.get("metricsQuery", "")
        c.check(all(t in mq for t in ("<<.Series>>", "<<.LabelMatchers>>", "<<.GroupBy>>")),
                f"rule {name}: metricsQuery uses <<.Series>>, <<.LabelMatchers>> and <<.GroupBy>>")
        series = re.match(r"\s*([a-zA-Z_:][a-zA-Z0-9_:]*)", r.get("seriesQuery", ""))
        rendered = (mq.replace("<<.Series>>", series.group(1) if series else "x")
                    .replace("<<.LabelMatchers>>", 'namespace="ns",pod=~"p-1|p-2"').replace("<<.GroupBy>>", "pod"))
        err = parse_promql(rendered)
        c.check(err is None, f"rule {name}: metricsQuery renders to valid PromQL", err or "")
        try:
            re.compile(r.get("name", {}).get("matches", ""))
            c.ok(f"rule {name}: name.matches is a valid regex")
        except re.error as e:
            c.fail(f"rule {name}: name.matches is a valid regex ({e})")
    return c.done()


# ---- Prometheus configuration and rules ----------------------------------------------------------------

RELABEL_ACTIONS = {"replace", "keep", "drop", "keepequal", "dropequal", "hashmod", "labelmap", "labeldrop",
                   "labelkeep", "lowercase", "uppercase"}
DURATION = re.compile(r"^(\d+(ms|s|m|h|d|w|y))+$")


def check_prometheus() -> int:
    c = Checker("prometheus")
    pdir = DEPLOY / "prometheus"
    cfg = load_yaml_docs(pdir / "prometheus.yml")[0]
    c.check(isinstance(cfg.get("global"), dict) and all(DURATION.match(str(v)) for v in cfg["global"].values()),
            "prometheus.yml: global intervals are durations")
    jobs = cfg.get("scrape_configs", [])
    names = [j.get("job_name") for j in jobs]
    c.check(bool(jobs) and len(set(names)) == len(names) and all(names), f"prometheus.yml: unique job names {names}")
    for j in jobs:
        jn = j.get("job_name")
        c.check(bool(j.get("static_configs") or j.get("kubernetes_sd_configs")), f"job {jn}: has targets or service discovery")
        for t in (t for sc in j.get("static_configs", []) for t in sc.get("targets", [])):
            c.check(bool(re.match(r"^[^:/\s]+:\d+$", t)), f"job {jn}: target {t} is host:port")
        for i, rc in enumerate(j.get("relabel_configs", [])):
            action = rc.get("action", "replace")
            try:
                re.compile(rc.get("regex", "(.*)"))
                ok = action in RELABEL_ACTIONS
            except re.error:
                ok = False
            c.check(ok, f"job {jn}: relabel rule {i} ({action}) has a known action and a valid regex")
    k8s_job = next((j for j in jobs if j.get("kubernetes_sd_configs")), None)
    if k8s_job:
        targets = {rc.get("target_label") for rc in k8s_job.get("relabel_configs", [])}
        c.check({"namespace", "pod"} <= targets, "kubernetes job adds the namespace and pod labels prometheus-adapter needs")
    for rf in cfg.get("rule_files", []):
        c.check((pdir / rf).is_file(), f"prometheus.yml: rule file {rf} exists")

    rules_doc = load_yaml_docs(pdir / "alerts.yml")[0]
    groups = rules_doc.get("groups", [])
    c.check(bool(groups) and len({g["name"] for g in groups}) == len(groups), "alerts.yml: groups with unique names")
    seen: set[str] = set()
    for g in groups:
        for r in g.get("rules", []):
            a = r.get("alert") or r.get("record")
            c.check(bool(a) and a not in seen, f"rule {a}: named and unique")
            seen.add(a)
            err = parse_promql(r.get("expr", ""))
            c.check(err is None, f"rule {a}: expr is valid PromQL", err or "")
            if "alert" in r:
                c.check(DURATION.match(str(r.get("for", "0s"))) is not None, f"rule {a}: 'for' is a duration")
                c.check(r.get("labels", {}).get("severity") in {"critical", "warning", "info"}, f"rule {a}: has a severity")
                c.check(bool(r.get("annotations", {}).get("summary")) and bool(r.get("annotations", {}).get("description")),
                        f"rule {a}: has summary and description")
    tests = pdir / "alerts.test.yml"
    if tests.is_file():
        t = load_yaml_docs(tests)[0]
        c.check(t.get("rule_files") == ["alerts.yml"], "alerts.test.yml tests alerts.yml")
        tested = {a["alertname"] for tc in t.get("tests", []) for a in tc.get("alert_rule_test", [])}
        c.check(tested <= seen, f"alerts.test.yml only names existing alerts {sorted(tested)}")
    return c.done()


# ---- Grafana dashboard ---------------------------------------------------------------------------------

GRAFANA_VARS = {"$__rate_interval": "5m", "$__interval": "1m", "$__range": "1h"}


def render_grafana_expr(expr: str, variables: set[str]) -> str:
    for k, v in GRAFANA_VARS.items():
        expr = expr.replace(k, v)
    for v in sorted(variables, key=len, reverse=True):
        expr = expr.replace("${" + v + "}", ".*").replace("$" + v, ".*")
    return expr


def check_grafana() -> int:
    c = Checker("grafana")
    path = DEPLOY / "grafana" / "holoface-dashboard.json"
    try:
        dash = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        c.fail(f"{rel(path)} parses as JSON ({e})")
        return c.done()
    c.ok(f"{rel(path)} parses as JSON")
    c.check(isinstance(dash.get("schemaVersion"), int) and 36 <= dash["schemaVersion"] <= 41,
            f"schemaVersion {dash.get('schemaVersion')} is a current Grafana schema")
    c.check(bool(dash.get("uid")) and bool(dash.get("title")), "dashboard has a uid and a title")
    variables = {v["name"] for v in dash.get("templating", {}).get("list", [])}
    panels = list(dash.get("panels", []))
    panels += [p for row in dash.get("panels", []) for p in row.get("panels", [])]
    ids = [p.get("id") for p in panels]
    c.check(bool(panels) and all(isinstance(i, int) for i in ids) and len(set(ids)) == len(ids),
            f"{len(panels)} panels, every id an integer and unique")
    cells: dict[tuple[int, int], int] = {}
    layout_ok = True
    for p in panels:
        g = p.get("gridPos", {})
        if not all(isinstance(g.get(k), int) for k in "hwxy") or g["x"] + g["w"] > 24:
            layout_ok = False
            continue
        for x in range(g["x"], g["x"] + g["w"]):
            for y in range(g["y"], g["y"] + g["h"]):
                if (x, y) in cells:
                    layout_ok = False
                cells[(x, y)] = p["id"]
    c.check(layout_ok, "every panel has a gridPos inside the 24-column grid and none overlap")
    for p in panels:
        if p.get("type") == "row":
            continue
        title = p.get("title", "?")
        targets = p.get("targets", [])
        c.check(bool(targets), f"panel '{title}' has queries")
        ds_uids = [p.get("datasource", {}).get("uid")] + [t.get("datasource", {}).get("uid") for t in targets]
        c.check(all(u and u.strip("${}") in variables for u in ds_uids), f"panel '{title}' uses the $datasource variable")
        for t in targets:
            err = parse_promql(render_grafana_expr(t.get("expr", ""), variables))
            c.check(err is None, f"panel '{title}' query {t.get('refId')} is valid PromQL", err or "")
    wanted = ["holoface_connected_clients", "holoface_frames_received_total", "holoface_frames_aligned_total",
              "holoface_frames_dropped_total", "holoface_queue_wait_seconds_bucket", "holoface_inference_seconds_bucket",
              "holoface_batch_size_sum", "holoface_queued_frames", "holoface_ready"]
    exprs = " ".join(t.get("expr", "") for p in panels for t in p.get("targets", []))
    missing = [m for m in wanted if m not in exprs]
    c.check(not missing, "dashboard shows clients, frame rates, drops by reason, queue wait, inference time, "
            "batch size, queued frames and readiness", f"missing: {missing}")
    return c.done()


# ---- metric names used anywhere vs. what the server exports -------------------------------------------

def check_metric_names() -> int:
    c = Checker("metrics")
    known = server_metric_names()
    if known is None:
        print(f"  skip  metrics: names check ({rel(METRICS_RS)} not found)")
        return 0
    sources = {
        "deploy/prometheus/alerts.yml": (DEPLOY / "prometheus" / "alerts.yml").read_text(),
        "deploy/grafana/holoface-dashboard.json": (DEPLOY / "grafana" / "holoface-dashboard.json").read_text(),
        "deploy/k8s/prometheus-adapter-rules.yaml": (K8S / "prometheus-adapter-rules.yaml").read_text(),
        "deploy/k8s/hpa.yaml": (K8S / "hpa.yaml").read_text(),
    }
    for name, text in sources.items():
        used = set(re.findall(r"\bholoface_[a-z_]+\b", text))
        # Histograms are exported as _bucket/_sum/_count of the name in metrics.rs.
        base = {re.sub(r"_(bucket|sum|count)$", "", u) if u not in known else u for u in used}
        unknown = sorted(u for u in base if u not in known)
        c.check(not unknown, f"{name}: the {len(used)} holoface_* metric names it uses are exported by the server",
                f"not in {rel(METRICS_RS)}: {unknown}")
    return c.done()


# ---- systemd unit --------------------------------------------------------------------------------------

def parse_unit(path: Path) -> dict[str, list[tuple[str, str]]]:
    sections: dict[str, list[tuple[str, str]]] = {}
    cur = None
    for line in path.read_text().splitlines():
        s = line.strip()
        if not s or s.startswith(("#", ";")):
            continue
        if s.startswith("[") and s.endswith("]"):
            cur = s[1:-1]
            sections.setdefault(cur, [])
        elif cur and "=" in s:
            k, v = s.split("=", 1)
            sections[cur].append((k.strip(), v.strip()))
    return sections


def seconds(v: str) -> float:
    total = 0.0
    for num, unit in re.findall(r"(\d+(?:\.\d+)?)\s*(ms|s|min|m|h)?", v):
        total += float(num) * {"ms": 0.001, "s": 1, "min": 60, "m": 60, "h": 3600, "": 1}[unit or ""]
    return total


def check_asset_paths(c: "Checker", cfg: dict, name: str) -> None:
    """A service's config names every asset by an absolute path: its user has no holoface data folder
    (systemd's dynamic user, the image's user without a home), so a default would not be found."""
    for section, key in [("engine", "model"), ("engine", "ort_dylib"), ("refine", "model")]:
        value = cfg.get(section, {}).get(key, "")
        c.check(value.startswith("/"), f"{name}: {section}.{key} is an absolute path ({value or 'unset'})")


def check_systemd() -> int:
    c = Checker("systemd")
    path = DEPLOY / "systemd" / "holoface-server.service"
    unit = parse_unit(path)
    svc = unit.get("Service", [])
    get = lambda k: [v for kk, v in svc if kk == k]  # noqa: E731
    one = lambda k: (get(k) or [""])[-1]  # noqa: E731
    c.check(one("Type") == "notify" and one("NotifyAccess") == "main", "Type=notify with NotifyAccess=main")
    c.check(one("Restart") == "on-failure" and bool(one("RestartSec")), "Restart=on-failure with RestartSec")
    unit_sec = unit.get("Unit", [])
    c.check(any(k == "StartLimitBurst" for k, _ in unit_sec) and any(k == "StartLimitIntervalSec" for k, _ in unit_sec),
            "start limits in [Unit]")
    cfg = tomllib.loads((DEPLOY / "systemd" / "server.toml").read_text())
    check_asset_paths(c, cfg, "systemd/server.toml")
    shutdown_s = cfg["limits"]["shutdown_timeout_ms"] / 1000
    c.check(seconds(one("TimeoutStopSec")) > shutdown_s,
            f"TimeoutStopSec={one('TimeoutStopSec')} is above limits.shutdown_timeout_ms ({shutdown_s:g} s)")
    c.check("--config /etc/holoface/server.toml" in one("ExecStart"), "ExecStart reads /etc/holoface/server.toml")
    creds = {v.split(":", 1)[0] for v in get("LoadCredential")}
    cred_dir = "/run/credentials/holoface-server.service/"
    used = [cfg["quic"]["cert"], cfg["quic"]["key"], cfg["auth"]["tokens_file"]]
    c.check(all(u.startswith(cred_dir) and u[len(cred_dir):] in creds for u in used),
            "server.toml's cert, key and tokens_file are the unit's LoadCredential= names")
    fp = cfg["quic"].get("fingerprint_file", "")
    c.check(not fp or (fp.startswith("/var/lib/") and fp.split("/")[3] in one("StateDirectory").split()),
            "fingerprint_file lies in the StateDirectory")
    for k, v in [("NoNewPrivileges", "yes"), ("ProtectSystem", "strict"), ("ProtectHome", "yes"), ("PrivateTmp", "yes"),
                 ("PrivateDevices", "yes"), ("ProtectKernelTunables", "yes"), ("ProtectKernelModules", "yes"),
                 ("ProtectKernelLogs", "yes"), ("ProtectControlGroups", "yes"), ("CapabilityBoundingSet", ""),
                 ("RestrictAddressFamilies", "AF_INET AF_INET6 AF_UNIX"), ("EnvironmentFile", "-/etc/holoface/server.env")]:
        c.check(one(k) == v, f"{k}={v}")
    c.check("@system-service" in get("SystemCallFilter"), "SystemCallFilter=@system-service")
    c.check(bool(one("LimitNOFILE")), "LimitNOFILE is set")
    c.check(bool(one("DynamicUser") == "yes" or one("User")), "runs as a dynamic or dedicated user")
    return c.done()


COMMANDS = {
    "toml": check_toml,
    "k8s": check_k8s,
    "adapter": check_adapter,
    "prometheus": check_prometheus,
    "grafana": check_grafana,
    "metrics": check_metric_names,
    "systemd": check_systemd,
}


def main(argv: list[str]) -> int:
    names = argv[1:] or list(COMMANDS)
    bad = [n for n in names if n not in COMMANDS]
    if bad:
        print(f"unknown check(s) {bad}; known: {list(COMMANDS)}", file=sys.stderr)
        return 2
    status = 0
    for n in names:
        try:
            status |= COMMANDS[n]()
        except Exception as e:  # noqa: BLE001 - a malformed file must fail the check, not crash unexplained
            print(f"  FAIL  {n}: could not check ({type(e).__name__}: {e})")
            status = 1
    return status


if __name__ == "__main__":
    sys.exit(main(sys.argv))
