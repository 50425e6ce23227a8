#!/usr/bin/env bash
# System packages for optional paths: EGL rasterization (libegl1 libegl-mesa0 libgl1-mesa-dri) and
# headless Chromium for the web viewer's screenshot test (chromium). Installs what is missing when
# run as root with apt-get; otherwise prints the command to run. Never fails the build: the library
# falls back to its pure-torch reference paths without EGL, and the browser test skips without Chromium.
set -u
pkgs=(libegl1 libegl-mesa0 libgl1-mesa-dri chromium)
missing=()
for p in "${pkgs[@]}"; do
  dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
done
[ ${#missing[@]} -eq 0 ] && exit 0
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
  echo "installing system packages: ${missing[*]}"
  export DEBIAN_FRONTEND=noninteractive
  (apt-get update -qq && apt-get install -y -qq --no-install-recommends "${missing[@]}") >/dev/null \
    || echo "warning: apt-get could not install ${missing[*]}; EGL rasterization or the browser test may be unavailable"
else
  echo "note: missing system packages ${missing[*]} (EGL rasterization, browser test); run: sudo apt-get install ${missing[*]}"
fi
exit 0
