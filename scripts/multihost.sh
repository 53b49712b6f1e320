#!/usr/bin/env bash
# Multi-host demo (issue 14): ga-ros play + vo_node, alignment_node and a mapping node on three
# Linux network namespaces joined by a bridge; Fast DDS over UDP between them. Needs root.
#   bash scripts/multihost.sh [--discovery multicast|peers] [--netem] [--rate R] [--out DIR]
# Everything (namespaces, veths, bridge, addresses 10.214.14.0/24) exists only inside the
# namespaces it creates and is deleted at the end, also on failure.
set -euo pipefail
cd "$(dirname "$0")/.."
if ! command -v ip >/dev/null 2>&1; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "[multihost] installing iproute2 (the ip and tc commands)" >&2
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq iproute2 >&2
  else
    echo "[multihost] needs the ip command: run as root, or: sudo apt-get install iproute2" >&2
    exit 2
  fi
fi
if [ "$(id -u)" != 0 ]; then
  echo "[multihost] network namespaces need root: sudo bash scripts/multihost.sh" >&2
  exit 2
fi
bash scripts/venv.sh
exec .venv/bin/python -m ga_ros.tools.multihost "$@"
