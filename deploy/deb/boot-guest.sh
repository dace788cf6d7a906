#!/bin/bash
# Inside the machine deploy/deb/boot-check.sh boots (as its boot-check.service): nori-robot's
# maintainer scripts against a running systemd and a running stack. Prints each step, then
# "NORI-BOOT-CHECK: PASS" or "NORI-BOOT-CHECK: FAILED: why" with what systemd did.
#   1. a first install enables the stack and starts nothing;
#   2. started, the units come up in the order they promise, and the driver keeps the bus the
#      trip record names latched off;
#   3. an upgrade with the stack running (one unit waiting out a restart after a crash, the
#      lidar stopped by its owner, the lift disabled);
#   4. a downgrade, with a stale restart record from an earlier upgrade left in /run;
#   5. an upgrade over a package whose prerm leaves the stack running (an earlier build);
#   6. an upgrade whose unpack fails (a file that cannot be replaced);
#   7. an upgrade whose old prerm fails;
#   8. an upgrade under a policy-rc.d that forbids starting services;
#   9. a removal, then a purge.
# After each change of version (change_to): the units that ran were stopped after the change
# began and before their programs were replaced, in the reverse of their start order, the
# driver turning torque off; exactly they run again, started in order, none restarted on its
# own, no process runs a replaced program, no restart record is left; the edited configuration
# and the trip record are kept byte for byte, and the new driver keeps the bus latched.
set -Eeuo pipefail
read -r n next </debs/versions
say() { echo "guest: $*"; }
fail() {
  echo "NORI-BOOT-CHECK: FAILED: $*"
  for u in supervisor bus-driver blackbox fleet-agent base lidar; do
    echo "nori-$u: $(systemctl show -p ActiveState -p NRestarts -p InactiveExitTimestampMonotonic \
      -p ActiveEnterTimestampMonotonic -p ActiveExitTimestampMonotonic \
      -p InactiveEnterTimestampMonotonic "nori-$u.service" | tr '\n' ' ')"
  done
  echo "what systemd did:"
  journalctl -b --no-pager -o short-monotonic _PID=1 | grep -E 'nori|boot-check-sim' | tail -60
  echo "the simulator:"
  journalctl -b --no-pager -o short-monotonic -u boot-check-sim | tail -10
  exit 1
}
trap 'fail "line $LINENO: $BASH_COMMAND"' ERR

dpkg_i() { dpkg -i --force-confold "/debs/nori-robot_$1_amd64.deb" "/debs/nori-sim_$1_amd64.deb" >"/tmp/$2.log" 2>&1; }
said() { grep -qF -- "$2" "/tmp/$1.log" || { cat "/tmp/$1.log"; fail "$1 did not say: $2"; }; }
installed() { dpkg-query -W -f '${Version}' nori-robot; }
# The nori units that run or are about to: the rule of deploy/deb/maintainer-common.sh, written
# again here on purpose (a check that sourced the scripts' rule could not catch it wrong).
running() { systemctl list-units --state=active,activating,deactivating,reloading --plain --no-legend 'nori-*.service' | awk '{print $1}' | sort | tr '\n' ' '; }
record=/run/nori/restart-after-upgrade
sums() { sha256sum /etc/nori/supervisor.toml /var/lib/nori/trips; }
now_us() { awk '{printf "%d", $1 * 1000000}' /proc/uptime; }
# A unit's timestamp: monotonic (µs since boot), or the wall clock's (µs since the epoch).
at() { systemctl show -P "${2}TimestampMonotonic" "nori-$1.service"; }
wall() { date -u -d "$(systemctl show --timestamp=us+utc -P "${2}Timestamp" "$1")" +%s%6N; }
# $1 had reached $2 no later than $3 had reached $4 (both set: a timestamp never set reads 0).
before() {
  local a b
  a=$(at "$1" "$2") b=$(at "$3" "$4")
  ((a > 0 && b > 0 && a <= b)) || fail "$1 $2 ($a) not before $3 $4 ($b)"
}

started_in_order() {
  before supervisor ActiveEnter bus-driver InactiveExit
  before supervisor ActiveEnter blackbox InactiveExit
  for u in fleet-agent base; do before bus-driver ActiveEnter "$u" InactiveExit; done
}
stopped_in_order() {
  before bus-driver InactiveEnter supervisor ActiveExit
  before blackbox InactiveEnter supervisor ActiveExit
  for u in fleet-agent base; do before "$u" InactiveEnter bus-driver ActiveExit; done
}
# Each unit of $1 stopped after $2 (µs since boot), the change's start.
stopped_since() {
  for u in $1; do
    (($(systemctl show -P InactiveEnterTimestampMonotonic "$u") > $2)) || fail "$u was not stopped by the change"
  done
}
# Each unit of $1 stopped before its program was replaced and, unless $2 is stays-down, started
# again after that.
replaced_while_down() {
  for u in $1; do
    local program replaced
    program=$(systemctl show -P ExecStart "$u" | sed 's/.*path=\([^ ;]*\).*/\1/')
    replaced=$(stat -c %.6Z "$program" | tr -d .)
    (($(wall "$u" InactiveEnter) <= replaced)) || fail "$u stopped after $program was replaced"
    [ "${2:-}" = stays-down ] || (($(wall "$u" ActiveEnter) >= replaced)) || fail "$u started before $program was replaced"
  done
}
# No process at all runs a replaced program, and no unit restarted on its own.
nothing_old_runs() {
  local exe
  for e in /proc/[0-9]*/exe; do
    exe=$(readlink "$e" 2>/dev/null) || continue
    [[ $exe != *" (deleted)" ]] || fail "${e%/exe} still runs the replaced $exe"
  done
  for u in $(running); do
    [ "$(systemctl show -P NRestarts "$u")" = 0 ] || fail "$u restarted on its own"
  done
}
# The driver now running keeps left_arm latched off by the trip record.
still_latched() {
  local id
  id=$(systemctl show -P InvocationID nori-bus-driver.service)
  journalctl --no-pager _SYSTEMD_INVOCATION_ID="$id" | grep -q 'latched off by a trip.*left_arm\|left_arm.*latched off by a trip' \
    || fail "the driver now running did not latch left_arm off"
}

# Installs $1 with the stack running and checks what must hold after a change of version (the
# header's list); $2 names the step's log. $3: a change expected to fail (its unpack).
change_to() {
  local ran t0 driver kept rc=0
  ran=$(running) t0=$(now_us) kept=$(sums)
  driver=$(systemctl show -P InvocationID nori-bus-driver.service)
  dpkg_i "$1" "$2" || rc=$?
  if [ "${3:-}" = fails ]; then
    [ $rc != 0 ] || { cat "/tmp/$2.log"; fail "$2: dpkg -i $1 succeeded"; }
  else
    [ $rc = 0 ] || { cat "/tmp/$2.log"; fail "$2: dpkg -i $1"; }
    [ "$(installed)" = "$1" ] || fail "$2: $1 not installed"
  fi
  sleep 3 # a new process that dies at once shows by now
  systemctl -q is-active boot-check-sim || fail "the simulator stopped during $2"
  [ "$(running)" = "$ran" ] || fail "ran: $ran; runs after $2: $(running)"
  stopped_since "$ran" "$t0"
  [ "${3:-}" = fails ] || replaced_while_down "$ran"
  [ ! -e "$record" ] || fail "the restart record outlived $2"
  [ "$(sums)" = "$kept" ] || fail "$2 changed the edited configuration or the trip record"
  nothing_old_runs
  stopped_in_order
  started_in_order
  journalctl --no-pager _SYSTEMD_INVOCATION_ID="$driver" | grep -q "stopped; torque off" \
    || fail "$2: the driver that ran did not stop with torque off"
  still_latched
}

say "systemd $(systemctl --version | sed -n 's/^systemd \([0-9]*\).*/\1/p') on $(systemd-detect-virt), $(nproc) CPUs; nori-robot $n and $next"
# Emulated (qemu without KVM), every process runs many times slower than on the robot, and a
# 1 s watchdog measures the emulator: it is lengthened here, outside the package (/run).
if [ "$(systemd-detect-virt)" = qemu ]; then
  for u in supervisor bus-driver fleet-agent base lift blackbox; do
    mkdir -p "/run/systemd/system/nori-$u.service.d"
    printf '[Service]\nWatchdogSec=30s\n' >"/run/systemd/system/nori-$u.service.d/emulated.conf"
  done
  say "emulated: each unit's watchdog lengthened to 30 s"
fi

say "1. first install of $n"
dpkg_i "$n" install || { cat /tmp/install.log; fail "dpkg -i $n"; }
said install "start it with: systemctl start nori.target"
[ "$(systemctl is-enabled nori.target)" = enabled ] || fail "nori.target not enabled"
[ -z "$(running)" ] || fail "a first install started $(running)"

say "2. the stack started, on the simulator, a bus latched by a trip"
install -o nori -g nori -m 644 /debs/calibration.toml /var/lib/nori/calibration.toml
printf 'left_elbow\n' >/var/lib/nori/trips && chown nori:nori /var/lib/nori/trips
printf '\n# edited on this robot\n' >>/etc/nori/supervisor.toml
# The owner keeps the lift out; the cameras are left out here (the simulator's four 720p
# streams would only load the machine).
systemctl disable --quiet nori-lift.service nori-camera@{head,neck,left_wrist,right_wrist}.service
# The simulator stands in for the hardware: run from its own copy, which no upgrade replaces.
install -D /usr/bin/nori-sim /usr/local/lib/boot-check/nori-sim
install -d -o nori -g nori /dev/nori
systemd-run --quiet --unit boot-check-sim -p User=nori -p Group=nori /usr/local/lib/boot-check/nori-sim --dir /dev/nori
for _ in $(seq 100); do [ -e /dev/nori/left_arm ] && break; sleep 0.2; done
[ -e /dev/nori/left_arm ] || fail "the simulator made no /dev/nori/left_arm"
systemctl start nori.target
stack="nori-base.service nori-blackbox.service nori-bus-driver.service nori-fleet-agent.service nori-lidar.service nori-supervisor.service "
sleep 3
[ "$(running)" = "$stack" ] || fail "started: $(running), not $stack"
nothing_old_runs
started_in_order
still_latched
say "   $(running | wc -w) units up in order, left_arm latched"

say "3. upgrade $n -> $next: the fleet agent waiting out a restart, the lidar stopped"
systemctl stop nori-lidar.service
mkdir -p /run/systemd/system/nori-fleet-agent.service.d
printf '[Service]\nRestartSec=10min\n' >/run/systemd/system/nori-fleet-agent.service.d/slow-restart.conf
systemctl daemon-reload
systemctl kill -s KILL nori-fleet-agent.service
for _ in $(seq 50); do [ "$(systemctl show -P SubState nori-fleet-agent)" = auto-restart ] && break; sleep 0.2; done
[ "$(systemctl show -P SubState nori-fleet-agent)" = auto-restart ] || fail "the fleet agent is not waiting out its restart"
change_to "$next" upgrade
said upgrade "nori-fleet-agent.service"
[ -e /etc/nori/supervisor.toml.dpkg-dist ] || fail "no new default beside the kept file"
rm /run/systemd/system/nori-fleet-agent.service.d/slow-restart.conf /etc/nori/supervisor.toml.dpkg-dist
systemctl daemon-reload
say "   stopped whole in order before the unpack, the same units started again in order"

say "4. downgrade $next -> $n, a stale record naming the lidar and the lift in /run"
mkdir -p /run/nori && printf 'nori-lidar.service\nnori-lift.service\n' >"$record"
change_to "$n" downgrade
said downgrade "downgrading from $next to $n"
said downgrade "kept: /var/lib/nori"
say "   said what it keeps, kept it; the stale record started nothing"

say "5. upgrade $n -> $next over a prerm that leaves the stack running"
printf '#!/bin/sh\nexit 0\n' >/var/lib/dpkg/info/nori-robot.prerm
change_to "$next" old-prerm
said old-prerm "still running before the unpack: stopping them"
say "   the new preinst stopped it before the unpack, and it was started again"

say "6. upgrade $next -> $n whose unpack fails"
chattr +i /usr/bin/nori-lift
change_to "$n" unpack-fails fails
chattr -i /usr/bin/nori-lift
[ "$(installed)" = "$next" ] || fail "a failed unpack left $(installed)"
said unpack-fails "the upgrade to $n failed"
say "   $next kept, and what ran runs again"

say "7. upgrade $next -> $n whose old prerm fails"
printf '#!/bin/sh\nexit 1\n' >/var/lib/dpkg/info/nori-robot.prerm
change_to "$n" prerm-fails
said prerm-fails "trying script from the new package instead"
say "   the new prerm stopped the stack, and it was started again"

say "8. upgrade $n -> $next under a policy-rc.d that forbids starting services"
printf '#!/bin/sh\nexit 101\n' >/usr/sbin/policy-rc.d && chmod 755 /usr/sbin/policy-rc.d
ran=$(running) t0=$(now_us)
dpkg_i "$next" policy || { cat /tmp/policy.log; fail "dpkg -i $next under policy-rc.d"; }
rm /usr/sbin/policy-rc.d
stopped_since "$ran" "$t0"
replaced_while_down "$ran" stays-down
[ -z "$(running)" ] || fail "policy-rc.d forbids starting, and $(running) run"
said policy "not started again"
[ ! -e "$record" ] || fail "the restart record outlived the upgrade under policy-rc.d"
nothing_old_runs
systemctl start nori.target
say "   stopped all the same, started nothing, and said so"

say "9. removal, then purge"
kept=$(sums)
dpkg -r nori-sim nori-robot >/tmp/remove.log 2>&1 || { cat /tmp/remove.log; fail "dpkg -r"; }
[ -z "$(running)" ] || fail "removed, and still running: $(running)"
[ "$(sums)" = "$kept" ] || fail "the removal changed the edited configuration or the trip record"
nothing_old_runs
dpkg --purge nori-sim nori-robot >/tmp/purge.log 2>&1 || { cat /tmp/purge.log; fail "purge"; }
said purge "/var/lib/nori (the trip record) is kept"
grep -qx left_elbow /var/lib/nori/trips || fail "the purge lost the trip record"
[ ! -e "$record" ] || fail "a restart record outlived the purge"
say "   removed: stopped, edits and the trip record kept; purged: /etc/nori gone, the trip record kept"

echo "NORI-BOOT-CHECK: PASS"
