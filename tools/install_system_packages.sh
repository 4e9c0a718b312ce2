#!/usr/bin/env bash
# Debian packages the project uses outside Python: espeak-ng and flite (sample speech,
# corpus), sox (corpus augmentation), PortAudio (live from a microphone: sounddevice loads
# it). Festival voices and fortunes are optional extras for building the full training
# corpus: pass --corpus to install them too.
set -euo pipefail
packages=(espeak-ng flite sox libportaudio2)
if [ "${1:-}" = "--corpus" ]; then
  packages+=(festival festvox-kallpc16k festvox-kdlpc16k festvox-us-slt-hts fortunes)
fi
missing=()
for p in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
[ "${#missing[@]}" -eq 0 ] && exit 0
sudo=""
[ "$(id -u)" -eq 0 ] || sudo="sudo"
echo "installing Debian packages: ${missing[*]}"
$sudo apt-get update -qq
DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
