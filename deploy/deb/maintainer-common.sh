# (Inlined by deploy/deb/build.sh where a maintainer script of nori-robot says #NORI_COMMON#:
# one rule for every script, as debhelper's own token is.)

# Every unit the package ships, as enabled, in an order their After= lines allow to start in:
# the postinst starts units again one by one in it (units started together, each in its own
# job, start in the order they were asked for, not the one their After= lines promise).
nori_units="nori.target nori-supervisor.service nori-bus-driver.service nori-fleet-agent.service
  nori-lidar.service nori-base.service nori-lift.service nori-blackbox.service
  nori-camera@head.service nori-camera@neck.service nori-camera@left_wrist.service
  nori-camera@right_wrist.service"

# The nori units that run or are about to: a unit waiting out its restart after a crash is
# `activating`, and counts.
nori_running() {
  systemctl list-units --state=active,activating,deactivating,reloading --plain --no-legend \
    'nori-*.service' | awk '{print $1}'
}

# Those of them to start again after an upgrade: not one its owner is stopping right now (a stop
# job queued or running).
nori_to_restart() {
  stopping=$(systemctl list-jobs --no-legend 2>/dev/null | awk '$3 == "stop" {print $2}')
  for unit in $(nori_running); do
    case " $(echo $stopping) " in *" $unit "*) ;; *) echo "$unit" ;; esac
  done
}

# What an upgrade stopped, for the new postinst to start again, and nothing else: added to a
# record already there (the old prerm's, when the new preinst finds units it left running). An
# upgrade's prerm drops an earlier record first; a removal's scripts drop it.
restart_record=/run/nori/restart-after-upgrade
remember_for_restart() {
  [ -n "$1" ] || return 0
  mkdir -p /run/nori
  { cat "$restart_record" 2>/dev/null || true; echo "$1"; } | tr ' ' '\n' | grep . | sort -u >"$restart_record.new"
  mv "$restart_record.new" "$restart_record"
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
