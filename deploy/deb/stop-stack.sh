# (Inlined by deploy/deb/build.sh where a maintainer script says #NORI_STOP_STACK#: the old
# package's prerm and the new package's preinst stop the stack by the same rule.)
# The nori units that run or are about to: a unit waiting out its restart after a crash is
# `activating`, and counts.
nori_running() {
  systemctl list-units --state=active,activating,deactivating,reloading --plain --no-legend \
    'nori-*.service' | awk '{print $1}'
}
# The whole stack stopped with systemctl, not deb-systemd-invoke (a policy-rc.d that forbids
# service actions must not let an old stack run on while its files are replaced); fails, naming
# them, if units are still up.
stop_stack() {
  # shellcheck disable=SC2046
  systemctl stop nori.target $(nori_running) || true
  still=$(nori_running)
  if [ -n "$still" ]; then
    echo "nori-robot: could not stop $(echo $still): not replacing a running stack" >&2
    return 1
  fi
}
