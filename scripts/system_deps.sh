#!/usr/bin/env bash
# Debian packages some tests use as real clients (they skip cleanly without them):
#   blender   imports the exported BVH files (tests/test_bvh.py)
#   chromium  renders data/eval/report.html headless (tests/evaluation/test_report_html.py)
# Installed with apt-get when missing and this runs as root; otherwise a note only.
# PARTY_NO_SYSTEM_DEPS=1 skips this step.
set -uo pipefail
[ -n "${PARTY_NO_SYSTEM_DEPS:-}" ] && exit 0
missing=()
command -v blender >/dev/null 2>&1 || missing+=(blender)
command -v chromium >/dev/null 2>&1 || missing+=(chromium)
[ ${#missing[@]} -eq 0 ] && exit 0
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  echo "installing ${missing[*]} (Debian packages, for the tests that use them) ..."
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}") \
    >/tmp/party_system_deps.log 2>&1 || echo "could not install ${missing[*]} (see /tmp/party_system_deps.log); their tests will skip"
else
  echo "note: ${missing[*]} not installed (not root or no apt-get); the tests that use them will skip"
fi
exit 0
