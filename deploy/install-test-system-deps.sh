#!/bin/sh
# System packages the service's browser test needs (Debian/Ubuntu): a headless chromium driven by
# Playwright's bundled driver through executable_path (no browser download).
#   sudo deploy/install-test-system-deps.sh
set -eu
SUDO=""
if [ "$(id -u)" != "0" ]; then SUDO="sudo"; fi
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
# Debian names it chromium; Ubuntu's chromium-browser is a snap shim, so prefer chromium when available.
if apt-cache show chromium >/dev/null 2>&1; then
    $SUDO apt-get install -y -qq --no-install-recommends chromium fonts-dejavu-core
else
    $SUDO apt-get install -y -qq --no-install-recommends chromium-browser fonts-dejavu-core
fi
command -v chromium || command -v chromium-browser
