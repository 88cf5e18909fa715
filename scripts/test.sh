#!/usr/bin/env bash
# Install what the tests need and run the whole suite under Xvfb.
#   bash scripts/test.sh [pytest options]
# Idempotent: Debian packages are installed only where missing (needs root or sudo), the virtual environment
# at .venv is created if absent, and the project is installed into it with its test extras.
set -euo pipefail
cd "$(dirname "$0")/.."

# Debian packages napari needs to render under Xvfb with Mesa (docs/design.md section 8).
pkgs=(xvfb xauth libgl1 libegl1 libgl1-mesa-dri libglx-mesa0 libxkbcommon-x11-0 libxcb-icccm4 libxcb-image0
      libxcb-keysyms1 libxcb-randr0 libxcb-render-util0 libxcb-xinerama0 libxcb-xkb1 libxcb-shape0
      libxcb-xfixes0 libxcb-cursor0 libdbus-1-3 libfontconfig1 libglib2.0-0)
missing=()
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ "${#missing[@]}" -gt 0 ]; then
  echo "installing Debian packages: ${missing[*]}"
  sudo=""; [ "$(id -u)" -eq 0 ] || sudo="sudo"
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

[ -x .venv/bin/python ] || python3 -m venv .venv
[ -x .venv/bin/uv ] || .venv/bin/python -m pip install -q --disable-pip-version-check uv
.venv/bin/uv pip install -q --python .venv/bin/python -e ".[test]"

# Lint first: a style error fails fast, before the long suite.
.venv/bin/ruff check napari_unwind services tests benchmarks

# napari and Qt need a real X server with GL (QT_QPA_PLATFORM=offscreen gives napari no GL context).
export QT_QPA_PLATFORM=xcb
exec xvfb-run -a -s "-screen 0 1600x1200x24" .venv/bin/python -m pytest "$@"
