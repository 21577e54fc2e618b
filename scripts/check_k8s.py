#!/usr/bin/env python3
"""Structural checks of the Kubernetes manifests (deploy/k8s) that a schema cannot see.

scripts/check-k8s.sh runs it after `kubernetes-validate --strict` (which checks the core kinds
against the Kubernetes OpenAPI schemas but skips, with a warning, kinds it has no schema for:
HTTPRoute, ScaledObject, ServiceMonitor). This script

  1. validates those CRD kinds against their upstream OpenAPI schemas, vendored in
     deploy/k8s/schemas/ (strict: unknown fields are errors; CEL rules are not evaluated), and
  2. checks how the objects fit together: per-pod routes for every ordinal the autoscaler may
     create, selectors, readiness semantics, drain vs. grace period, probes, the route prefix...

Usage:
  scripts/check_k8s.py                      build every overlay with kubectl kustomize and check
  scripts/check_k8s.py --built dev=FILE ... check already built overlays (what check-k8s.sh does)
  scripts/check_k8s.py --self-test          also break each key property in memory and require
                                            that its check fails
  scripts/check_k8s.py --extract-crd-schema CRD.yaml VERSION   print a vendored schema

Exit status: 0 when every check passes, 1 when one fails, 2 on a usage or environment error.
"""

import argparse
import copy
import json
import os
import re
import shutil
import subprocess
import sys

try:
    import yaml
except ImportError:  # pragma: no cover
    sys.exit("error: PyYAML is missing: python3 -m pip install pyyaml")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
K8S = os.path.join(ROOT, "deploy", "k8s")
OVERLAYS = os.path.join(K8S, "overlays")
SCHEMAS = os.path.join(K8S, "schemas")
GENERATOR = os.path.join(K8S, "gen-pod-routes.py")
GENERATED = os.path.join(K8S, "components", "pod-routes", "pod-routes.generated.yaml")

# The overlay whose maxReplicaCount the committed generated routes must match.
PROD = "prod"

# CRD kinds kubernetes-validate has no schema for, and the vendored schema of each.
CRD_SCHEMAS = {
    ("gateway.networking.k8s.io/v1", "HTTPRoute"): "gateway.networking.k8s.io_httproute_v1.json",
    ("keda.sh/v1alpha1", "ScaledObject"): "keda.sh_scaledobject_v1alpha1.json",
    ("monitoring.coreos.com/v1", "ServiceMonitor"): "monitoring.coreos.com_servicemonitor_v1.json",
}
# Core kinds (checked by kubernetes-validate against the Kubernetes schemas).
CORE_KINDS = {
    ("v1", "ConfigMap"), ("v1", "Service"), ("v1", "Secret"), ("v1", "PersistentVolumeClaim"),
    ("apps/v1", "StatefulSet"), ("policy/v1", "PodDisruptionBudget"),
}

POD_NAME_LABEL = "statefulset.kubernetes.io/pod-name"
POD_INDEX_FIELD = "metadata.labels['apps.kubernetes.io/pod-index']"
# Time a process needs after its drain deadline to send `bye` and exit, on top of the drain
# timeout and the preStop sleep, before the kubelet's SIGKILL.
GRACE_MARGIN_S = 5
SERVER_DEFAULT_DRAIN_S = 300  # voxlight serve --drain-timeout-s default
GATEWAY_MAX_RULES = 16


class Failures:
    """Collects failed checks as (check id, overlay, message)."""

    def __init__(self):
        self.items = []

    def fail(self, check, overlay, message):
        self.items.append((check, overlay, message))

    def ids(self):
        return {c for c, _, _ in self.items}


# --------------------------------------------------------------------------- helpers


def load_docs(text):
    return [d for d in yaml.safe_load_all(text) if d]


def build_overlay(name):
    if shutil.which("kubectl") is None:
        sys.stderr.write("error: kubectl not found on PATH; install kubectl >= 1.28 (it carries "
                         "kustomize): https://kubernetes.io/docs/tasks/tools/\n")
        sys.exit(2)
    path = os.path.join(OVERLAYS, name)
    out = subprocess.run(["kubectl", "kustomize", path], capture_output=True, text=True)
    if out.returncode != 0:
        sys.stderr.write(f"error: kubectl kustomize {path} failed:\n{out.stderr}")
        sys.exit(1)
    return load_docs(out.stdout)


def of_kind(docs, kind):
    return [d for d in docs if d.get("kind") == kind]


def name_of(doc):
    return doc.get("metadata", {}).get("name", "")


def ns_of(doc):
    return doc.get("metadata", {}).get("namespace")


def parse_duration_s(value):
    return int(value)


def flags_of(args):
    """--flag=value and --flag value -> {flag: value}; bare flags -> True."""
    flags = {}
    i = 0
    while i < len(args):
        a = args[i]
        if a.startswith("--"):
            if "=" in a:
                k, v = a[2:].split("=", 1)
                flags[k] = v
            elif i + 1 < len(args) and not args[i + 1].startswith("--"):
                flags[a[2:]] = args[i + 1]
                i += 1
            else:
                flags[a[2:]] = True
        i += 1
    return flags


class Workload:
    """The StatefulSet, its voxlight container and its args with $(VAR)s resolved."""

    def __init__(self, sts, docs):
        self.sts = sts
        self.name = name_of(sts)
        self.pod_spec = sts["spec"]["template"]["spec"]
        self.pod_labels = sts["spec"]["template"].get("metadata", {}).get("labels", {}) or {}
        containers = self.pod_spec.get("containers", [])
        self.container = next((c for c in containers if c.get("name") == "voxlight"),
                              containers[0] if containers else {})
        configmaps = {name_of(c): c.get("data", {}) or {} for c in of_kind(docs, "ConfigMap")}
        self.env = {}  # name -> resolved string, or ("fieldRef", path), or None (unresolvable)
        for e in self.container.get("env", []) or []:
            if "value" in e:
                self.env[e["name"]] = str(e["value"])
            elif "valueFrom" in e:
                vf = e["valueFrom"]
                if "fieldRef" in vf:
                    self.env[e["name"]] = ("fieldRef", vf["fieldRef"].get("fieldPath"))
                elif "configMapKeyRef" in vf:
                    ref = vf["configMapKeyRef"]
                    self.env[e["name"]] = configmaps.get(ref.get("name"), {}).get(ref.get("key"))
                else:
                    self.env[e["name"]] = None
        self.raw_args = [str(a) for a in (self.container.get("command", []) or [])
                         + (self.container.get("args", []) or [])]
        self.raw_flags = flags_of(self.raw_args)
        self.flags = {k: self.resolve(v) if isinstance(v, str) else v
                      for k, v in self.raw_flags.items()}

    def resolve(self, text):
        def sub(m):
            v = self.env.get(m.group(1))
            if isinstance(v, str):
                return v
            return m.group(0)  # fieldRefs and unresolvable refs stay symbolic
        return re.sub(r"\$\(([A-Za-z_][A-Za-z0-9_]*)\)", sub, text)

    def container_ports(self):
        return {p.get("name"): p.get("containerPort")
                for p in self.container.get("ports", []) or []}


def selector_matches(selector, labels):
    return all(labels.get(k) == v for k, v in (selector or {}).items())


def strictify(schema):
    """additionalProperties: false wherever a CRD object schema lists its properties (the API
    server would prune unknown fields silently; kubectl's strict field validation rejects them)."""
    if isinstance(schema, dict):
        if (schema.get("type") == "object" and "properties" in schema
                and "additionalProperties" not in schema
                and not schema.get("x-kubernetes-preserve-unknown-fields")):
            schema["additionalProperties"] = False
        for v in schema.values():
            strictify(v)
    elif isinstance(schema, list):
        for v in schema:
            strictify(v)
    return schema


_validators = {}


def crd_validator(schema_file):
    if schema_file not in _validators:
        import jsonschema  # installed with kubernetes-validate
        with open(os.path.join(SCHEMAS, schema_file), encoding="utf-8") as f:
            schema = strictify(json.load(f))
        schema.pop("$comment", None)
        _validators[schema_file] = jsonschema.Draft7Validator(schema)
    return _validators[schema_file]


# --------------------------------------------------------------------------- the checks


def check_overlay(overlay, docs, f: Failures):
    # Kinds: every object is either a core kind (kubernetes-validate) or a vendored CRD kind.
    for d in docs:
        key = (d.get("apiVersion"), d.get("kind"))
        if key in CRD_SCHEMAS:
            errors = sorted(crd_validator(CRD_SCHEMAS[key]).iter_errors(d),
                            key=lambda e: list(e.absolute_path))
            for e in errors[:5]:
                path = ".".join(str(p) for p in e.absolute_path)
                f.fail("crd-schema", overlay, f"{key[1]}/{name_of(d)}: {path}: {e.message}")
        elif key not in CORE_KINDS:
            f.fail("kinds", overlay, f"{key[1]}/{name_of(d)} ({key[0]}): no schema check covers "
                   "this kind; add it to CORE_KINDS or vendor its CRD schema")

    sets = of_kind(docs, "StatefulSet")
    if len(sets) != 1:
        f.fail("statefulset", overlay, f"expected exactly one StatefulSet, found {len(sets)}")
        return
    w = Workload(sets[0], docs)
    services = {name_of(s): s for s in of_kind(docs, "Service")}
    routes = of_kind(docs, "HTTPRoute")
    scaled = of_kind(docs, "ScaledObject")
    monitors = of_kind(docs, "ServiceMonitor")

    # StatefulSet basics.
    spec = w.sts["spec"]
    if spec.get("podManagementPolicy") != "Parallel":
        f.fail("statefulset", overlay, "podManagementPolicy must be Parallel (a full pod is not "
               "ready on purpose; OrderedReady would block scaling behind it)")
    if not selector_matches(spec.get("selector", {}).get("matchLabels"), w.pod_labels):
        f.fail("selectors", overlay, "the StatefulSet's selector does not match its pod labels")
    headless = services.get(spec.get("serviceName"))
    if headless is None or headless["spec"].get("clusterIP") != "None":
        f.fail("statefulset", overlay, f"serviceName {spec.get('serviceName')!r} must name a "
               "headless Service (clusterIP: None) in the same build")

    # Services select this StatefulSet's pods; per-pod ones exactly one pod by name.
    per_pod = {}  # ordinal -> Service
    for name, svc in services.items():
        sel = dict(svc["spec"].get("selector") or {})
        if not sel:
            f.fail("selectors", overlay, f"Service {name} has no selector")
            continue
        pod_name = sel.pop(POD_NAME_LABEL, None)
        if not selector_matches(sel, w.pod_labels):
            f.fail("selectors", overlay, f"Service {name} selector {sel} does not match the "
                   f"StatefulSet's pod labels {w.pod_labels}")
        if pod_name is not None:
            m = re.fullmatch(re.escape(w.name) + r"-(\d+)", str(pod_name))
            if not m:
                f.fail("selectors", overlay, f"Service {name} selects pod-name {pod_name!r}, not "
                       f"a pod of StatefulSet {w.name} ({w.name}-<ordinal>)")
                continue
            n = int(m.group(1))
            if name != f"{w.name}-pod-{n}":
                f.fail("per-pod-services", overlay, f"Service {name} selects {pod_name} but "
                       f"should be named {w.name}-pod-{n}")
            if n in per_pod:
                f.fail("per-pod-services", overlay, f"two Services select {pod_name}")
            per_pod[n] = svc
        else:
            ports = [p.get("targetPort") for p in svc["spec"].get("ports", [])]
            for tp in ports:
                if tp not in w.container_ports() and tp not in w.container_ports().values():
                    f.fail("selectors", overlay, f"Service {name} targets port {tp!r}, which the "
                           "container does not expose")
    for pdb in of_kind(docs, "PodDisruptionBudget"):
        if not selector_matches(pdb["spec"].get("selector", {}).get("matchLabels"), w.pod_labels):
            f.fail("selectors", overlay, f"PodDisruptionBudget {name_of(pdb)} selects no pod")

    # Per-pod Services publish not-ready addresses (a full/draining pod serves its sessions);
    # the Service new sessions enter through must not.
    for n, svc in per_pod.items():
        if svc["spec"].get("publishNotReadyAddresses") is not True:
            f.fail("not-ready", overlay, f"Service {name_of(svc)} must set "
                   "publishNotReadyAddresses: true (full and draining pods serve their sessions)")
    root_backends = set()
    for r in routes:
        for rule in r["spec"].get("rules", []) or []:
            for m in rule.get("matches", []) or []:
                p = m.get("path", {})
                if p.get("type") == "PathPrefix" and p.get("value") == "/":
                    root_backends |= {b.get("name") for b in rule.get("backendRefs", []) or []}
    if not routes and w.name in services:
        root_backends.add(w.name)
    if not root_backends & set(services):
        f.fail("routes", overlay, f"no Service for new sessions (a `/` route rule to a Service, "
               f"or a Service named {w.name})")
    for b in root_backends:
        svc = services.get(b)
        if svc is None:
            f.fail("routes", overlay, f"the `/` rule points at Service {b}, which is not built")
        elif svc["spec"].get("publishNotReadyAddresses"):
            f.fail("not-ready", overlay, f"Service {b} takes new sessions and must not publish "
                   "not-ready addresses (a full or draining pod would get new sessions)")

    # Drain: grace period > drain timeout + preStop sleep (+ margin to send `bye` and exit).
    grace = w.pod_spec.get("terminationGracePeriodSeconds", 30)
    drain_flag = w.flags.get("drain-timeout-s")
    if drain_flag is None:
        drain = SERVER_DEFAULT_DRAIN_S
    else:
        try:
            drain = int(drain_flag)
        except (TypeError, ValueError):
            f.fail("grace-period", overlay, f"--drain-timeout-s={drain_flag!r} does not resolve "
                   "to a number (missing ConfigMap key or env var?)")
            drain = None
    pre_stop = (w.container.get("lifecycle") or {}).get("preStop")
    sleep_s = None
    if pre_stop is None:
        f.fail("prestop", overlay, "no preStop hook: the endpoint removal must reach the Gateway "
               "before the server starts refusing new sessions")
        sleep_s = 0
    elif "sleep" in pre_stop:
        sleep_s = int(pre_stop["sleep"].get("seconds", 0))
    else:
        cmd = (pre_stop.get("exec") or {}).get("command") or []
        if len(cmd) == 2 and os.path.basename(str(cmd[0])) == "sleep" and str(cmd[1]).isdigit():
            sleep_s = int(cmd[1])
        else:
            f.fail("prestop", overlay, f"preStop {pre_stop} is not a plain sleep")
            sleep_s = 0
    if drain is not None and grace < drain + sleep_s + GRACE_MARGIN_S:
        f.fail("grace-period", overlay, f"terminationGracePeriodSeconds {grace} must exceed drain "
               f"timeout {drain} + preStop sleep {sleep_s} (+{GRACE_MARGIN_S} s to say `bye` and "
               "exit), or the kubelet kills sessions mid-drain")

    # Probes: /healthz (startup, liveness) and /readyz (readiness) on the container's port.
    ports = w.container_ports()
    listen = str(w.flags.get("listen", ""))
    listen_port = int(listen.rsplit(":", 1)[1]) if re.fullmatch(r".*:\d+", listen) else None
    if listen_port is None or listen_port not in ports.values():
        f.fail("probes", overlay, f"--listen={listen!r} does not match a containerPort {ports}")
    for probe, path in (("startupProbe", "/healthz"), ("livenessProbe", "/healthz"),
                        ("readinessProbe", "/readyz")):
        p = w.container.get(probe)
        get = (p or {}).get("httpGet")
        if not get:
            f.fail("probes", overlay, f"{probe} missing or not an httpGet")
            continue
        if get.get("path") != path:
            f.fail("probes", overlay, f"{probe} checks {get.get('path')!r}, must be {path}")
        port = get.get("port")
        number = ports.get(port) if isinstance(port, str) else port
        if number is None or number != listen_port:
            f.fail("probes", overlay, f"{probe} port {port!r} is not the port voxlight listens "
                   f"on ({listen_port})")

    # Autoscaler: targets this StatefulSet; owns the replica count; scales down slowly.
    max_replicas = None
    for so in scaled:
        ref = so["spec"].get("scaleTargetRef", {})
        if (ref.get("kind"), ref.get("apiVersion"), ref.get("name")) != ("StatefulSet", "apps/v1",
                                                                          w.name):
            f.fail("autoscaler", overlay, f"ScaledObject {name_of(so)} targets {ref}, not "
                   f"apps/v1 StatefulSet {w.name}")
        lo = so["spec"].get("minReplicaCount", 0)
        max_replicas = so["spec"].get("maxReplicaCount", 100)
        if lo < 1:
            f.fail("autoscaler", overlay, "minReplicaCount must be >= 1 (nothing would serve `/`)")
        if max_replicas < lo:
            f.fail("autoscaler", overlay, "maxReplicaCount < minReplicaCount")
        if "replicas" in spec:
            f.fail("autoscaler", overlay, "the StatefulSet sets spec.replicas although KEDA scales "
                   "it: every `kubectl apply` would reset the size and drain pods")
        down = (so["spec"].get("advanced", {}).get("horizontalPodAutoscalerConfig", {})
                .get("behavior", {}).get("scaleDown", {}))
        if down.get("stabilizationWindowSeconds", 300) < grace:
            f.fail("autoscaler", overlay, f"scaleDown.stabilizationWindowSeconds "
                   f"{down.get('stabilizationWindowSeconds', 300)} < grace period {grace}")
        for pol in down.get("policies", []) or [{"periodSeconds": 15}]:
            if pol.get("periodSeconds", 0) < grace:
                f.fail("autoscaler", overlay, f"scaleDown policy {pol} lets pods go faster than one "
                       f"drain ({grace} s)")
        for t in so["spec"].get("triggers", []):
            if t.get("type") != "prometheus":
                continue
            md = t.get("metadata", {})
            q = md.get("query", "")
            if "voxlight_sessions_active" not in q:
                f.fail("autoscaler", overlay, "the Prometheus query does not use "
                       "voxlight_sessions_active")
            for nsq in re.findall(r'namespace="([^"]*)"', q):
                if nsq != ns_of(so):
                    f.fail("autoscaler", overlay, f"the query reads namespace {nsq!r} but the "
                           f"ScaledObject is in {ns_of(so)!r}")
            try:
                threshold = float(md.get("threshold", "nan"))
            except ValueError:
                threshold = float("nan")
            cap = w.flags.get("max-sessions")
            if "voxlight_session_capacity" in q:
                if not 0 < threshold <= 1:
                    f.fail("autoscaler", overlay, f"threshold {md.get('threshold')} on a "
                           "sessions/capacity query must be a fraction in (0, 1]")
            elif not (str(cap).isdigit() and 0 < threshold <= int(cap)):
                f.fail("autoscaler", overlay, f"threshold {md.get('threshold')} must be a target "
                       f"sessions per pod in (0, --max-sessions={cap}]")
            if str(md.get("ignoreNullValues", "true")).lower() != "false":
                f.fail("autoscaler", overlay, "ignoreNullValues must be \"false\": an empty "
                       "result (Prometheus lost its targets) would otherwise scale down to min")

    # Per-pod routes: one Service + one rewriting rule per ordinal the StatefulSet may have.
    pod_rules = {}  # ordinal -> (route name, rule)
    for r in routes:
        rules = r["spec"].get("rules", []) or []
        if len(rules) > GATEWAY_MAX_RULES:
            f.fail("routes", overlay, f"HTTPRoute {name_of(r)} has {len(rules)} rules; Gateway "
                   f"API allows {GATEWAY_MAX_RULES}")
        if not r["spec"].get("parentRefs"):
            f.fail("routes", overlay, f"HTTPRoute {name_of(r)} has no parentRefs")
        for rule in rules:
            for m in rule.get("matches", []) or []:
                p = m.get("path", {})
                mm = re.fullmatch(r"/p/(\d+)/", str(p.get("value", "")))
                if not mm:
                    continue
                n = int(mm.group(1))
                if p.get("type") != "PathPrefix":
                    f.fail("routes", overlay, f"{p.get('value')} must be a PathPrefix match")
                if n in pod_rules:
                    f.fail("routes", overlay, f"two rules match /p/{n}/")
                pod_rules[n] = (name_of(r), rule)
    has_pod_routing = bool(per_pod or pod_rules)
    if has_pod_routing:
        expected = max_replicas if max_replicas is not None else spec.get("replicas", 1)
        want = set(range(expected))
        for label, have in (("per-pod Services", set(per_pod)), ("/p/<n>/ route rules",
                                                                   set(pod_rules))):
            if have != want:
                missing = sorted(want - have)
                extra = sorted(have - want)
                f.fail("per-pod-services", overlay, f"{label} cover ordinals {sorted(have)}, need "
                       f"0..{expected - 1} (maxReplicas {expected}); missing {missing}, stale "
                       f"{extra}: run deploy/k8s/gen-pod-routes.py --max-replicas {expected}")
        for n, (rname, rule) in sorted(pod_rules.items()):
            rewrites = [x for x in rule.get("filters", []) or [] if x.get("type") == "URLRewrite"]
            path = (rewrites[0].get("urlRewrite", {}).get("path", {}) if rewrites else {})
            if path.get("type") != "ReplacePrefixMatch" or path.get("replacePrefixMatch") != "/":
                f.fail("routes", overlay, f"HTTPRoute {rname}: /p/{n}/ must be rewritten with "
                       "URLRewrite ReplacePrefixMatch `/` (the server expects the prefix "
                       "stripped)")
            backends = rule.get("backendRefs", []) or []
            names = [b.get("name") for b in backends]
            if names != [f"{w.name}-pod-{n}"]:
                f.fail("routes", overlay, f"HTTPRoute {rname}: /p/{n}/ must go to exactly Service "
                       f"{w.name}-pod-{n}, not {names}")
            for b in backends:
                svc = services.get(b.get("name"))
                if svc and b.get("port") not in [p.get("port") for p in svc["spec"]["ports"]]:
                    f.fail("routes", overlay, f"HTTPRoute {rname}: port {b.get('port')} is not a "
                           f"port of Service {b.get('name')}")

    # Route prefix: /p/$(POD_INDEX)/ with POD_INDEX from the pod-index label, iff routed per pod.
    prefix = w.raw_flags.get("route-prefix")
    if has_pod_routing:
        if prefix != "/p/$(POD_INDEX)/":
            f.fail("route-prefix", overlay, f"--route-prefix is {prefix!r}; the routes expect "
                   "/p/$(POD_INDEX)/")
        if w.env.get("POD_INDEX") != ("fieldRef", POD_INDEX_FIELD):
            f.fail("route-prefix", overlay, f"POD_INDEX must come from fieldRef {POD_INDEX_FIELD} "
                   f"(got {w.env.get('POD_INDEX')!r})")
    elif prefix not in (None, "/"):
        f.fail("route-prefix", overlay, f"--route-prefix={prefix} without per-pod routes: nothing "
               "would route or strip it")

    # GPU: a GPU request comes with the taint toleration and Vulkan's driver capability; a pod
    # without one must not get the image's NVIDIA_VISIBLE_DEVICES=all.
    limits = (w.container.get("resources") or {}).get("limits") or {}
    gpus = {k: v for k, v in limits.items() if k.startswith("nvidia.com/")}
    tolerations = w.pod_spec.get("tolerations") or []
    if gpus:
        if not any(t.get("key") == "nvidia.com/gpu" for t in tolerations):
            f.fail("gpu", overlay, "a GPU is requested but the nvidia.com/gpu taint is not "
                   "tolerated")
        if "graphics" not in str(w.env.get("NVIDIA_DRIVER_CAPABILITIES", "")):
            f.fail("gpu", overlay, "NVIDIA_DRIVER_CAPABILITIES must include graphics (Vulkan)")
    elif w.env.get("NVIDIA_VISIBLE_DEVICES") not in ("void", "none"):
        f.fail("gpu", overlay, "no GPU requested: set NVIDIA_VISIBLE_DEVICES=void, or the image's "
               "`all` hands every GPU of an nvidia-runtime node to this pod")

    # Security context.
    psc = w.pod_spec.get("securityContext") or {}
    csc = w.container.get("securityContext") or {}
    if not (psc.get("runAsNonRoot") or csc.get("runAsNonRoot")):
        f.fail("security", overlay, "runAsNonRoot is not set")
    if (csc.get("runAsUser") or psc.get("runAsUser")) != 10001:
        f.fail("security", overlay, "runAsUser must be 10001 (the image's voxlight user)")
    if csc.get("readOnlyRootFilesystem") is not True:
        f.fail("security", overlay, "readOnlyRootFilesystem must be true")
    if csc.get("allowPrivilegeEscalation") is not False:
        f.fail("security", overlay, "allowPrivilegeEscalation must be false")
    if "ALL" not in ((csc.get("capabilities") or {}).get("drop") or []):
        f.fail("security", overlay, "capabilities must drop ALL")

    # Volumes: --data is a read-only mount; --tokens-file lives in a mounted Secret.
    mounts = {m["mountPath"]: m for m in w.container.get("volumeMounts", []) or []}
    volumes = {v["name"]: v for v in w.pod_spec.get("volumes", []) or []}
    data = w.flags.get("data")
    if data and (data not in mounts or not mounts[data].get("readOnly")):
        f.fail("data", overlay, f"--data={data} must be a read-only volume mount")
    tokens_file = w.flags.get("tokens-file")
    if tokens_file:
        mount = next((m for p, m in mounts.items() if tokens_file.startswith(p.rstrip("/") + "/")),
                     None)
        secret = volumes.get(mount["name"], {}).get("secret") if mount else None
        if secret is None:
            f.fail("tokens", overlay, f"--tokens-file={tokens_file} is not in a mounted Secret")
        elif secret.get("optional"):
            f.fail("tokens", overlay, f"Secret {secret.get('secretName')} holds --tokens-file but "
                   "is optional: without it the server would crash-loop instead of waiting")

    # Metrics: scrape every pod exactly once, with a token when the server wants one.
    for sm in monitors:
        sel = sm["spec"].get("selector", {}).get("matchLabels", {})
        chosen = [s for s in services.values()
                  if selector_matches(sel, s.get("metadata", {}).get("labels", {}) or {})]
        if len(chosen) != 1:
            f.fail("servicemonitor", overlay, f"ServiceMonitor {name_of(sm)} selects "
                   f"{[name_of(s) for s in chosen]}: it must select exactly one Service (each pod "
                   "is behind several; more would count its sessions more than once)")
        for s in chosen:
            if s["spec"].get("publishNotReadyAddresses") is not True:
                f.fail("servicemonitor", overlay, f"Service {name_of(s)} (scraped) must publish "
                       "not-ready addresses, so full and draining pods are counted")
        for ep in sm["spec"].get("endpoints", []):
            if ep.get("path", "/metrics") != "/metrics":
                f.fail("servicemonitor", overlay, f"scrapes {ep.get('path')}, not /metrics")
            for s in chosen:
                if ep.get("port") not in [p.get("name") for p in s["spec"]["ports"]]:
                    f.fail("servicemonitor", overlay, f"port {ep.get('port')!r} is not a named "
                           f"port of Service {name_of(s)}")
            authorized = bool(ep.get("authorization") or ep.get("bearerTokenSecret"))
            if bool(tokens_file) != authorized:
                f.fail("tokens", overlay, "tokens " + ("on" if tokens_file else "off") + " but the "
                       "ServiceMonitor " + ("sends no" if not authorized else "sends a") + " token")

    return max_replicas


def check_generated(max_replicas, f: Failures):
    out = subprocess.run([sys.executable, GENERATOR, "--max-replicas", str(max_replicas),
                          "--stdout"], capture_output=True, text=True)
    if out.returncode != 0:
        f.fail("generated", PROD, f"{GENERATOR} failed: {out.stderr.strip()}")
        return
    with open(GENERATED, encoding="utf-8") as fh:
        committed = fh.read()
    if committed != out.stdout:
        f.fail("generated", PROD, f"{os.path.relpath(GENERATED, ROOT)} differs from "
               f"gen-pod-routes.py --max-replicas {max_replicas} (the {PROD} overlay's "
               f"maxReplicaCount): run deploy/k8s/gen-pod-routes.py --max-replicas {max_replicas}")


def run_checks(built):
    f = Failures()
    prod_max = None
    for overlay, docs in built.items():
        m = check_overlay(overlay, docs, f)
        if overlay == PROD:
            prod_max = m
    if PROD in built:
        if prod_max is None:
            f.fail("autoscaler", PROD, "the prod overlay has no ScaledObject (maxReplicaCount "
                   "sizes the generated routes)")
        else:
            check_generated(prod_max, f)
    return f


# --------------------------------------------------------------------------- self-test


def _sts(docs):
    return of_kind(docs, "StatefulSet")[0]


def _ctr(docs):
    return _sts(docs)["spec"]["template"]["spec"]["containers"][0]


def _named(docs, kind, name):
    return next(d for d in docs if d.get("kind") == kind and name_of(d) == name)


def _replace_arg(docs, prefix, value):
    c = _ctr(docs)
    c["args"] = [value if a.startswith(prefix) else a for a in c["args"]]


def _set_config(docs, key, value):
    for cm in of_kind(docs, "ConfigMap"):
        if key in cm.get("data", {}):
            cm["data"][key] = value


def _drop_last_pod_service(docs):
    n = max(int(name_of(s).rsplit("-", 1)[1]) for s in of_kind(docs, "Service")
            if name_of(s).startswith("voxlight-pod-"))
    docs.remove(_named(docs, "Service", f"voxlight-pod-{n}"))


def _pod_route_rule(docs, n=0):
    return _named(docs, "HTTPRoute", f"voxlight-pod-{n}")["spec"]["rules"][0]


MUTATIONS = [
    # (overlay, expected failing check, what is broken, mutation)
    (PROD, "per-pod-services", "the last ordinal's per-pod Service removed", _drop_last_pod_service),
    (PROD, "per-pod-services", "maxReplicaCount raised above the generated ordinals",
     lambda d: of_kind(d, "ScaledObject")[0]["spec"].update(maxReplicaCount=9)),
    (PROD, "selectors", "per-pod Service selects a pod of another StatefulSet",
     lambda d: _named(d, "Service", "voxlight-pod-1")["spec"]["selector"]
     .update({POD_NAME_LABEL: "other-1"})),
    (PROD, "selectors", "root Service selector misses the pod labels",
     lambda d: _named(d, "Service", "voxlight")["spec"]["selector"]
     .update({"app.kubernetes.io/name": "voxlite"})),
    (PROD, "not-ready", "per-pod Service stops publishing not-ready addresses",
     lambda d: _named(d, "Service", "voxlight-pod-2")["spec"]
     .update(publishNotReadyAddresses=False)),
    (PROD, "not-ready", "root Service publishes not-ready addresses",
     lambda d: _named(d, "Service", "voxlight")["spec"].update(publishNotReadyAddresses=True)),
    (PROD, "grace-period", "drain timeout raised to the grace period",
     lambda d: _set_config(d, "drain-timeout-s", "330")),
    (PROD, "grace-period", "grace period below drain + preStop",
     lambda d: _sts(d)["spec"]["template"]["spec"].update(terminationGracePeriodSeconds=300)),
    (PROD, "prestop", "preStop hook removed", lambda d: _ctr(d).pop("lifecycle")),
    (PROD, "autoscaler", "ScaledObject targets a Deployment",
     lambda d: of_kind(d, "ScaledObject")[0]["spec"]["scaleTargetRef"].update(kind="Deployment")),
    (PROD, "autoscaler", "ScaledObject targets another name",
     lambda d: of_kind(d, "ScaledObject")[0]["spec"]["scaleTargetRef"].update(name="voxlite")),
    (PROD, "autoscaler", "StatefulSet keeps spec.replicas under KEDA",
     lambda d: _sts(d)["spec"].update(replicas=2)),
    (PROD, "autoscaler", "scale-down stabilization shorter than a drain",
     lambda d: of_kind(d, "ScaledObject")[0]["spec"]["advanced"]["horizontalPodAutoscalerConfig"]
     ["behavior"]["scaleDown"].update(stabilizationWindowSeconds=60)),
    (PROD, "autoscaler", "query reads another namespace",
     lambda d: of_kind(d, "ScaledObject")[0]["spec"]["triggers"][0]["metadata"].update(
         query='sum(voxlight_sessions_active{namespace="default"})')),
    (PROD, "autoscaler", "threshold above capacity on a sessions/capacity query",
     lambda d: of_kind(d, "ScaledObject")[0]["spec"]["triggers"][0]["metadata"]
     .update(threshold="24")),
    (PROD, "probes", "readiness probe on /healthz",
     lambda d: _ctr(d)["readinessProbe"]["httpGet"].update(path="/healthz")),
    (PROD, "probes", "liveness probe on /readyz (a full pod would be restarted)",
     lambda d: _ctr(d)["livenessProbe"]["httpGet"].update(path="/readyz")),
    (PROD, "probes", "startup probe on another port",
     lambda d: _ctr(d)["startupProbe"]["httpGet"].update(port=9090)),
    (PROD, "routes", "per-pod rule without the prefix rewrite",
     lambda d: _pod_route_rule(d, 3).pop("filters")),
    (PROD, "routes", "per-pod rule rewrites to /ws instead of /",
     lambda d: _pod_route_rule(d, 3)["filters"][0]["urlRewrite"]["path"]
     .update(replacePrefixMatch="/ws")),
    (PROD, "routes", "per-pod rule sends /p/4/ to pod 5",
     lambda d: _pod_route_rule(d, 4)["backendRefs"][0].update(name="voxlight-pod-5")),
    (PROD, "route-prefix", "route prefix without POD_INDEX",
     lambda d: _replace_arg(d, "--route-prefix", "--route-prefix=/p/0/")),
    (PROD, "route-prefix", "POD_INDEX from the pod name instead of the pod-index label",
     lambda d: next(e for e in _ctr(d)["env"] if e["name"] == "POD_INDEX")["valueFrom"]["fieldRef"]
     .update(fieldPath="metadata.name")),
    (PROD, "crd-schema", "HTTPRoute rewrite misspelled (replacePrefix)",
     lambda d: _pod_route_rule(d, 0)["filters"][0]["urlRewrite"]["path"]
     .update(replacePrefix="/")),
    (PROD, "crd-schema", "ScaledObject with an unknown field",
     lambda d: of_kind(d, "ScaledObject")[0]["spec"].update(maxReplicas=8)),
    (PROD, "servicemonitor", "ServiceMonitor selects every voxlight Service",
     lambda d: of_kind(d, "ServiceMonitor")[0]["spec"]["selector"]["matchLabels"]
     .pop("voxlight/service")),
    (PROD, "tokens", "tokens on, ServiceMonitor without a token",
     lambda d: of_kind(d, "ServiceMonitor")[0]["spec"]["endpoints"][0].pop("authorization")),
    (PROD, "tokens", "tokens file in an optional Secret",
     lambda d: next(v for v in _sts(d)["spec"]["template"]["spec"]["volumes"]
                    if v["name"] == "tokens")["secret"].update(optional=True)),
    (PROD, "gpu", "GPU requested without the taint toleration",
     lambda d: _sts(d)["spec"]["template"]["spec"].pop("tolerations")),
    (PROD, "security", "root filesystem writable",
     lambda d: _ctr(d)["securityContext"].update(readOnlyRootFilesystem=False)),
    ("dev", "route-prefix", "dev passes a route prefix nothing strips",
     lambda d: _ctr(d)["args"].append("--route-prefix=/p/$(POD_INDEX)/")),
    ("dev", "gpu", "dev without NVIDIA_VISIBLE_DEVICES=void",
     lambda d: _ctr(d).update(env=[e for e in _ctr(d)["env"]
                                   if e["name"] != "NVIDIA_VISIBLE_DEVICES"])),
]


def self_test(built):
    """Each mutation must make its check fail, and only the mutated overlay is rechecked."""
    ok = True
    for overlay, check, what, mutate in MUTATIONS:
        if overlay not in built:
            continue
        docs = copy.deepcopy(built[overlay])
        mutate(docs)
        f = Failures()
        m = check_overlay(overlay, docs, f)
        if overlay == PROD and m is not None and check == "generated":
            check_generated(m, f)
        seen = check in f.ids()
        ok &= seen
        detail = next((msg for c, _, msg in f.items if c == check), "NOT DETECTED")
        print(f"self-test {'ok  ' if seen else 'FAIL'} [{check}] {overlay}: {what}: {detail}")
    return ok


# --------------------------------------------------------------------------- CLI


def extract_crd_schema(path, version):
    with open(path, encoding="utf-8") as fh:
        crd = yaml.safe_load(fh)

    def drop_descriptions(x):
        if isinstance(x, dict):
            return {k: drop_descriptions(v) for k, v in x.items()
                    if not (k == "description" and isinstance(v, str))}
        if isinstance(x, list):
            return [drop_descriptions(v) for v in x]
        return x

    v = next(v for v in crd["spec"]["versions"] if v["name"] == version)
    schema = drop_descriptions(v["schema"]["openAPIV3Schema"])
    group, kind = crd["spec"]["group"], crd["spec"]["names"]["kind"]
    bundle = (crd["metadata"].get("annotations") or {})
    schema = {"$comment": f"{kind}.{group}/{version} openAPIV3Schema from {os.path.basename(path)} "
              f"{bundle.get('gateway.networking.k8s.io/bundle-version', '')}".rstrip()
              + "; descriptions removed. See deploy/k8s/schemas/README.md.", **schema}
    json.dump(schema, sys.stdout, indent=1, sort_keys=True)
    sys.stdout.write("\n")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--built", action="append", default=[], metavar="OVERLAY=FILE",
                        help="an overlay already built with kubectl kustomize (repeatable)")
    parser.add_argument("--self-test", action="store_true",
                        help="also break each key property in memory; each must be detected")
    parser.add_argument("--extract-crd-schema", nargs=2, metavar=("CRD_YAML", "VERSION"))
    parser.add_argument("--list-crd-kinds", action="store_true",
                        help="print `apiVersion kind` of each CRD kind validated here")
    args = parser.parse_args()

    if args.list_crd_kinds:
        for api_version, kind in sorted(CRD_SCHEMAS):
            print(api_version, kind)
        return 0

    if args.extract_crd_schema:
        extract_crd_schema(*args.extract_crd_schema)
        return 0

    built = {}
    if args.built:
        for item in args.built:
            overlay, _, path = item.partition("=")
            with open(path, encoding="utf-8") as fh:
                built[overlay] = load_docs(fh.read())
    else:
        for overlay in sorted(os.listdir(OVERLAYS)):
            built[overlay] = build_overlay(overlay)

    f = run_checks(built)
    for overlay, docs in built.items():
        kinds = sorted({d["kind"] for d in docs})
        crds = sum(1 for d in docs if (d.get("apiVersion"), d.get("kind")) in CRD_SCHEMAS)
        print(f"check_k8s: {overlay}: {len(docs)} objects ({', '.join(kinds)}); "
              f"{crds} CRD objects validated against deploy/k8s/schemas")
    for check, overlay, message in f.items:
        print(f"FAIL [{check}] {overlay}: {message}")
    ok = not f.items
    if args.self_test:
        if f.items:
            print("self-test skipped: fix the failures above first")
        else:
            ok &= self_test(built)
    print("check_k8s: " + ("all checks passed" if ok else "FAILED"))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
