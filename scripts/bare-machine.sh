#!/usr/bin/env bash
# Makes this machine bare again for the checkout's set-up: removes every package `make test`'s set-up installs
# with apt (the Makefile's APT_PACKAGES) and the packages only they pulled in, and the checkout's own venv and data
# folder. `.ci/run` runs it first under CI=true, so that a set-up step ordered after the step that needs it fails
# in CI instead of hiding behind packages an earlier run left installed (issue 51). Download caches (apt's
# archives, pip's and cargo's) are kept: a bare machine reaches the same registries, and this tests the order of
# the steps, not the network.
set -euo pipefail
cd "$(dirname "$0")/.."
read -r -a pkgs <<<"$(make -s --no-print-directory print-APT_PACKAGES)"
installed=()
for p in "${pkgs[@]}"; do
    if dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'ok installed'; then installed+=("$p"); fi
done
SUDO=$([ "$(id -u)" = 0 ] || echo sudo)
if [ ${#installed[@]} -gt 0 ]; then
    echo "bare-machine: removing ${installed[*]} and what only they needed"
    export DEBIAN_FRONTEND=noninteractive
    $SUDO apt-get remove -y -qq "${installed[@]}" >/dev/null
    $SUDO apt-get autoremove -y -qq >/dev/null
else
    echo "bare-machine: none of the set-up's apt packages is installed"
fi
rm -rf .venv .cache
