#!/bin/sh
# System packages the service's tests need (Debian/Ubuntu): a headless chromium driven by Playwright's
# bundled driver through executable_path (no browser download), and the PostgreSQL server, of which the
# PostgreSQL test starts a throwaway cluster (initdb + pg_ctl, unix socket in a temporary directory; as a
# non-root user: the 'postgres' account the package creates when the tests run as root).
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
# only the server binaries are needed: the package's own cluster is not used (the test runs its own)
$SUDO apt-get install -y -qq --no-install-recommends postgresql
ls -d /usr/lib/postgresql/*/bin/initdb
