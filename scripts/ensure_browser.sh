#!/usr/bin/env bash
# Chromium and chromedriver for the viewer's browser test (tests/apps/viewer/test_browser.py):
# installed with apt-get when missing and this user may; otherwise the test skips and says why.
set -u
if command -v chromedriver >/dev/null && { command -v chromium >/dev/null || command -v chromium-browser >/dev/null; }; then
  exit 0
fi
if [ -n "${SAGONLINE_NO_BROWSER_INSTALL:-}" ]; then
  echo "ensure_browser: SAGONLINE_NO_BROWSER_INSTALL is set: nothing installed; the browser test will skip" >&2
  exit 0
fi
if ! command -v apt-get >/dev/null; then
  echo "ensure_browser: no apt-get here; the browser test will skip (install chromium and chromedriver)" >&2
  exit 0
fi
SUDO=""
if [ "$(id -u)" -ne 0 ]; then
  if sudo -n true 2>/dev/null; then SUDO="sudo -n"; else
    echo "ensure_browser: not root and no sudo; the browser test will skip" >&2
    exit 0
  fi
fi
echo "ensure_browser: installing Debian's chromium and chromium-driver with apt-get${SUDO:+ (sudo)} for the" >&2
echo "  viewer's browser test: system packages, about 300 MB (SAGONLINE_NO_BROWSER_INSTALL=1 skips this) ..." >&2
export DEBIAN_FRONTEND=noninteractive
# a line every 15 s while apt-get works (it is silent for about a minute otherwise)
( start=$(date +%s); while sleep 15; do
    echo "ensure_browser: still installing ($(( $(date +%s) - start )) s) ..." >&2
  done ) &
ticker=$!
trap 'kill "$ticker" 2>/dev/null' EXIT
$SUDO apt-get update -qq >/dev/null 2>&1
$SUDO apt-get install -y -qq chromium chromium-driver >/dev/null 2>&1 \
  || echo "ensure_browser: apt-get could not install chromium; the browser test will skip" >&2
kill "$ticker" 2>/dev/null
echo "ensure_browser: done" >&2
exit 0
