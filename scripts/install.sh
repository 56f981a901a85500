#!/usr/bin/env bash
# Installs OSVI Studio's system packages (headless EGL/OSMesa rendering, Chromium for browser tests)
# and its Python environment in .venv. Safe to run repeatedly: it does only what is missing.
#
# Options (environment variables; the defaults give everything `./run serve` and `./run test` need):
#   STUDIO_EXTRAS   pip extras of the package to install, comma-separated (default: test). Empty installs
#                   the runtime only, without pytest, playwright, ruff, mypy, ... (the Docker image does).
#   STUDIO_BROWSER  1 (default) installs Chromium for the browser tests; 0 skips it.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

extras="${STUDIO_EXTRAS-test}"  # unset: test; set to "" : none
browser="${STUDIO_BROWSER:-1}"
case "$browser" in
  0 | 1) ;;
  *) echo "[install] STUDIO_BROWSER must be 0 or 1, got '$browser'" >&2; exit 2 ;;
esac
if [[ ! "$extras" =~ ^[A-Za-z0-9_,-]*$ ]]; then
  echo "[install] STUDIO_EXTRAS must be comma-separated extra names, got '$extras'" >&2
  exit 2
fi

apt_pkgs=(libegl1 libegl-mesa0 libgl1-mesa-dri libgl1 libglx-mesa0 libosmesa6 openssl)  # openssl: `studio bus credentials`
if [ "$browser" = 1 ]; then apt_pkgs+=(chromium); fi
missing=()
for p in "${apt_pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ "${#missing[@]}" -gt 0 ]; then
  echo "[install] system packages: ${missing[*]}"
  sudo_cmd=""
  [ "$(id -u)" -ne 0 ] && sudo_cmd="sudo"
  $sudo_cmd apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

py="${PYTHON:-python3.11}"
command -v "$py" >/dev/null || py=python3
# The stamp names what was installed: pyproject.toml's hash, and the extras when they are not the default
# (so switching between a runtime and a test environment reinstalls, and the default stamp is unchanged).
stamp=".venv/.installed-$(sha256sum pyproject.toml | cut -c1-16)"
[ "$extras" = test ] || stamp="$stamp-extras-${extras:-none}"
if [ -n "$extras" ]; then spec=".[$extras]"; else spec="."; fi
if [ ! -f "$stamp" ]; then
  echo "[install] python environment (.venv) with $($py --version), installing $spec"
  start=$(date +%s)
  [ -x .venv/bin/python ] || "$py" -m venv .venv
  .venv/bin/pip install -q --upgrade pip
  .venv/bin/pip install -q -e "$spec"
  rm -f .venv/.installed-*
  touch "$stamp"
  echo "[install] done in $(( $(date +%s) - start )) s"
fi
