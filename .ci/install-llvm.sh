#!/usr/bin/env bash
# Best effort: Mitsuba's fast CPU variant (llvm_ad_rgb) needs an LLVM shared library that
# Dr.Jit accepts; Debian's libllvm19 works. Without it prtlab falls back to scalar_rgb.
set -u
if ls /usr/lib/x86_64-linux-gnu/libLLVM-19.so* >/dev/null 2>&1 || ls /usr/lib/x86_64-linux-gnu/libLLVM.so.19* >/dev/null 2>&1; then
  exit 0
fi
if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19) >/dev/null 2>&1 \
    && echo "installed libllvm19 for Mitsuba's llvm_ad_rgb variant" \
    || echo "could not install libllvm19; Mitsuba will use scalar_rgb"
fi
exit 0
