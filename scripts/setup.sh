#!/usr/bin/env bash
# Installs everything the tests and the checks need on a fresh Debian machine. Idempotent:
#  - Mesa's Vulkan CPU driver (lavapipe) + the Vulkan loader, when no Vulkan ICD is installed;
#  - a Python 3.11 venv ($PII_VENV, default <repo>/.venv) with Blender-as-a-module and usd-core;
#  - the Khronos glTF-Validator from npm (scripts/node_modules).
set -euo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="${PII_VENV:-$repo/.venv}"

say() { echo "[setup] $*" >&2; }

# 1. Vulkan CPU driver.
if ! ls /usr/share/vulkan/icd.d/*.json >/dev/null 2>&1 || ! ldconfig -p | grep -q libvulkan.so.1; then
  if [ "$(id -u)" = 0 ]; then
    say "installing mesa-vulkan-drivers libvulkan1"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq >/dev/null
    apt-get install -y -qq mesa-vulkan-drivers libvulkan1 >/dev/null
  else
    say "no Vulkan driver and not root: run 'sudo apt-get install mesa-vulkan-drivers libvulkan1'"
    exit 1
  fi
fi

# 2. Python venv (Blender as a module needs Python 3.11).
py="${PII_SETUP_PYTHON:-python3.11}"
command -v "$py" >/dev/null 2>&1 || py=python3
if [ ! -x "$venv/bin/python" ] || ! "$venv/bin/python" -c 'import bpy, pxr, numpy' >/dev/null 2>&1; then
  say "creating Python venv at $venv (bpy, usd-core, numpy)"
  "$py" -m venv "$venv"
  "$venv/bin/python" -m pip install -q --upgrade pip >/dev/null
  "$venv/bin/python" -m pip install -q -r "$repo/scripts/requirements.txt"
fi

# 3. glTF validator.
if [ ! -f "$repo/scripts/node_modules/gltf-validator/package.json" ]; then
  say "installing gltf-validator (npm)"
  (cd "$repo/scripts" && npm ci --silent --no-audit --no-fund >/dev/null)
fi
say "ok: vulkan $(ls /usr/share/vulkan/icd.d/ | tr '\n' ' '), python $("$venv/bin/python" -c 'import sys,bpy;print(sys.version.split()[0], "bpy", bpy.app.version_string)'), gltf-validator $(node -p 'require("'"$repo"'/scripts/node_modules/gltf-validator/package.json").version')"
