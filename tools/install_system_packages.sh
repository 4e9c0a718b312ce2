#!/usr/bin/env bash
# Debian packages the project and its tests use outside Python: espeak-ng, flite and festival
# with its US voices (speech synthesis, corpus), fortunes (the corpus's English texts), sox
# (corpus augmentation), PortAudio (live from a microphone: sounddevice loads it), ffmpeg
# (audio formats libsndfile cannot read, checking rendered videos) and, when `node` or `npm`
# is not on PATH, Node.js and npm (the glTF validator of tools/install_node_tools.sh).
# Installs what is missing, then checks that everything is there: exits 1 naming what is not.
# --screenshots adds what the docs' panel pictures need and no test does: Debian's Blender 3.4
# with numpy, and Xvfb for its window (tools/panel_screenshot.py, tools/docs_figures.py panel).
# --corpus is still accepted (it used to add festival and fortunes, now always installed).
set -euo pipefail
packages=(espeak-ng flite sox libportaudio2 ffmpeg fortunes festival festvox-kallpc16k festvox-kdlpc16k festvox-us-slt-hts)
for arg in "$@"; do
  case "$arg" in
    --corpus) ;;
    --screenshots) packages+=(blender python3-numpy xvfb) ;;
    *) echo "install_system_packages.sh: unknown option $arg" >&2; exit 2 ;;
  esac
done
# Node.js may come from elsewhere (nodesource, nvm): Debian's only when there is none
command -v node >/dev/null && command -v npm >/dev/null || packages+=(nodejs npm)

not_installed() {
  local p
  for p in "${packages[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || echo "$p"
  done
}
mapfile -t missing < <(not_installed)
if [ "${#missing[@]}" -gt 0 ]; then
  sudo=""
  [ "$(id -u)" -eq 0 ] || sudo="sudo"
  echo "installing Debian packages: ${missing[*]}"
  $sudo apt-get update -qq || true
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends \
    -o DPkg::Lock::Timeout=300 "${missing[@]}" >/dev/null || true
  mapfile -t missing < <(not_installed)
fi
for program in node npm; do
  command -v "$program" >/dev/null || missing+=("$program (program)")
done
if [ "${#missing[@]}" -gt 0 ]; then
  echo "install_system_packages.sh: not installed: ${missing[*]} (install them with apt-get and rerun)" >&2
  exit 1
fi
