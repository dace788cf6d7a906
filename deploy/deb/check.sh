#!/usr/bin/env bash
# The packages as a robot gets them: installed into a fresh Debian bookworm root (the oldest
# Raspberry Pi OS the stack supports), checked, run, and upgraded.
#
#   deploy/deb/check.sh ARCH BIN_DIR
#
# builds version N and N+1 of nori-robot and nori-sim from BIN_DIR (deploy/deb/build.sh), then
# in a fresh root of ARCH (amd64 natively; arm64 through qemu-aarch64, deploy/arm64/cross.sh
# registers it):
#   1. dpkg -i of N succeeds; the nori user, /var/lib/nori and the enabled units are there;
#      `systemd-analyze verify` accepts every unit;
#   2. the packaged binaries run the stack on the simulator (`nori up --run-for`);
#   3. an edited /etc/nori file and a trip record are written, N+1 is installed over N: both
#      are kept byte for byte, and the new version is the installed one;
#   4. N is installed over N+1 (a downgrade): it says what it keeps, and keeps it;
#   5. from the fleet's signed repository (deploy/apt/repo.sh, served by nginx on loopback):
#      N on stable, N+1 on beta; beta's index served as stable, a tampered index and a
#      tampered package are refused and change nothing; a plain apt-get upgrade leaves the
#      held stack alone; on stable nori-upgrade finds nothing to do; on beta it upgrades to
#      N+1, keeping what step 3 kept and naming the new default, and the packaged agent says
#      it runs N+1.
# Needs root (debootstrap, chroot, mounts). The pristine root is cached in
# $NORI_DEB_CHECK_CACHE (/var/tmp/nori-deb-check); each run starts from a fresh copy.
#
#   deploy/deb/check.sh --prepare ARCH
#
# only fetches what the check needs (the host's debootstrap, lintian, nginx, reprepro and
# gpg, and the pristine root), so CI can do it while it builds.
set -euo pipefail
cd "$(dirname "$0")/../.."
usage() { sed -n '2,28p' "$0" | sed 's/^# \{0,1\}//' >&2; exit 2; }
[ $# -eq 2 ] || usage
cache=${NORI_DEB_CHECK_CACHE:-/var/tmp/nori-deb-check}
mirror=${NORI_DEBIAN_MIRROR:-http://deb.debian.org/debian}
say() { echo "deb-check: $*" >&2; }
fail() { echo "deb-check: FAILED: $*" >&2; exit 1; }

# The host's tools and the pristine root of `$1`.
prepare() {
  local tools=()
  command -v debootstrap >/dev/null || tools+=(debootstrap)
  command -v lintian >/dev/null || tools+=(lintian)
  command -v nginx >/dev/null || tools+=(nginx-light)
  # deploy/apt/repo.sh's (it installs them itself when run alone).
  command -v reprepro >/dev/null || tools+=(reprepro)
  command -v gpg >/dev/null || tools+=(gpg)
  if ((${#tools[@]})); then
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${tools[@]}" >/dev/null
  fi
  pristine=$cache/bookworm-$1.tar
  [ ! -s "$pristine" ] || return 0
  say "debootstrap bookworm $1 (once; cached in $pristine)"
  local tmp
  tmp=$(mktemp -d)
  debootstrap --variant=minbase --arch="$1" --include=systemd,udev bookworm "$tmp" "$mirror" >/dev/null
  mkdir -p "$cache" && tar -C "$tmp" -cf "$pristine.part" . && mv "$pristine.part" "$pristine"
  rm -rf "$tmp"
}
if [ "$1" = --prepare ]; then
  prepare "$2"
  exit
fi
arch=$1 bin_dir=$2
prepare "$arch"

work=$(mktemp -d)
root=$work/root
mounts=()
server=
cleanup() {
  [ -z "$server" ] || kill "$server" 2>/dev/null || true
  for m in "${mounts[@]}"; do umount "$m" 2>/dev/null || true; done
  rm -rf "$work"
}
trap cleanup EXIT
mkdir "$root" && tar -C "$root" -xf "$pristine"
# A robot's / is 755 (debootstrap's folder was mktemp's 700): apt's _apt user and nginx's
# workers (step 5) must get through it and through $work.
chmod 755 "$root" "$work"
for m in proc dev dev/pts; do
  case $m in proc) mount -t proc proc "$root/proc" ;; *) mount --bind "/$m" "$root/$m" ;; esac
  mounts=("$root/$m" "${mounts[@]}")
done
in_root() { chroot "$root" env -i PATH=/usr/sbin:/usr/bin:/sbin:/bin HOME=/root LANG=C.UTF-8 "$@"; }

# shellcheck source=deploy/deb/two-versions.sh
. deploy/deb/two-versions.sh
build_two_versions "$arch" "$bin_dir" "$work"
mkdir "$root/debs" && cp "$work"/n/*.deb "$work"/next/*.deb "$root/debs/"

say "0. lintian"
# Every warning it would give is either fixed or overridden with its reason
# (deploy/deb/*.lintian-overrides).
said=$(lintian "$work"/n/*.deb 2>&1 | grep -v "running with root privileges" || true)
[ -z "$said" ] || { echo "$said" >&2; fail "lintian"; }
say "   lintian: nothing"

say "1. install $n"
in_root dpkg -i "/debs/nori-robot_${n}_$arch.deb" "/debs/nori-sim_${n}_$arch.deb" >"$work/install.log" 2>&1 \
  || { cat "$work/install.log" >&2; fail "dpkg -i"; }
grep -q "start it with: systemctl start nori.target" "$work/install.log" || fail "no word on starting it"
in_root getent passwd nori | grep -q ':/var/lib/nori:' || fail "no nori user"
[ "$(in_root stat -c %U "/var/lib/nori")" = nori ] || fail "/var/lib/nori is not nori's"
for u in nori-supervisor nori-bus-driver nori-fleet-agent nori-lidar nori-base nori-lift nori-blackbox \
  nori-camera@head nori-camera@neck nori-camera@left_wrist nori-camera@right_wrist; do
  [ -L "$root/etc/systemd/system/nori.target.wants/$u.service" ] || fail "$u not enabled"
done
[ -L "$root/etc/systemd/system/multi-user.target.wants/nori.target" ] || fail "nori.target not enabled"
in_root sh -c 'cd /usr/lib/systemd/system && cp nori-camera@.service /tmp/nori-camera@head.service &&
  systemd-analyze verify --man=no nori-supervisor.service nori-bus-driver.service \
    nori-fleet-agent.service nori-lidar.service nori-base.service nori-lift.service nori-blackbox.service \
    /tmp/nori-camera@head.service nori.target' >"$work/verify.log" 2>&1 \
  || { cat "$work/verify.log" >&2; fail "systemd-analyze verify"; }
# It exits 0 on a key it ignores, but names the unit: ours must draw no word at all.
if grep -i nori "$work/verify.log" >&2; then fail "systemd-analyze verify"; fi
# The robot's calibration is its own state: the driver reads it from /var/lib/nori, and until
# `nori calibrate` wrote it there the driver refuses to start, saying so.
grep -qx 'calibration-file = "/var/lib/nori/calibration.toml"' "$root/etc/nori/bus-driver.toml" \
  || fail "the packaged bus-driver.toml does not name /var/lib/nori/calibration.toml"
[ ! -e "$root/etc/nori/calibration.toml" ] || fail "the simulated A3's calibration shipped in /etc/nori"
if in_root bus-driver --config /etc/nori/bus-driver.toml --run-for 1 >"$work/uncalibrated.log" 2>&1; then
  fail "the driver started on a robot never calibrated"
fi
grep -q "not calibrated yet" "$work/uncalibrated.log" || { cat "$work/uncalibrated.log" >&2; fail "the driver did not say the robot is not calibrated"; }
# ... while the tool that calibrates it loads the same configuration (found by the outside
# review: it refused too); here it gets as far as the bus's device, which this root has not.
if in_root nori calibrate by-hand left_arm --within 1 >"$work/calibrate.log" 2>&1; then
  fail "nori calibrate ran with no bus"
fi
grep -q "cannot open /dev/nori/left_arm" "$work/calibrate.log" \
  || { cat "$work/calibrate.log" >&2; fail "nori calibrate did not reach the bus on a robot never calibrated"; }
say "   installed: the user, /var/lib/nori, 11 units enabled and verified; the driver refuses to start uncalibrated"

say "2. the packaged stack on the simulator"
in_root nori up --dir /tmp/nori-up --domain "nori_debcheck_$$" --run-for 8 >"$work/up.log" 2>&1 \
  || { tail -30 "$work/up.log" >&2; fail "nori up"; }
for said in "bus-driver stopped (exit status: 0)" "supervisor stopped (exit status: 0)" \
  "restarts: simulator 0, supervisor 0, bus-driver 0"; do
  grep -qF "$said" "$work/up.log" || { tail -30 "$work/up.log" >&2; fail "nori up did not say: $said"; }
done
say "   nori up ran the stack for 8 s: no restart, every process stopped cleanly"

say "3. upgrade $n -> $next, keeping an edited configuration and a trip record"
printf '\n# edited on this robot\n' >>"$root/etc/nori/supervisor.toml"
printf 'left_elbow\n' >"$root/var/lib/nori/trips"
# The owner keeps the lift out of the stack; the upgrade must not bring it back.
in_root systemctl disable nori-lift.service >/dev/null 2>&1
sum() { (cd "$root" && sha256sum etc/nori/supervisor.toml var/lib/nori/trips); }
before=$(sum)
# --force-confold, as a fleet upgrades (nori-upgrade): the package's supervisor.toml changed
# and so did the robot's; the robot's is kept, the new default left beside it.
in_root dpkg -i --force-confold "/debs/nori-robot_${next}_$arch.deb" "/debs/nori-sim_${next}_$arch.deb" >"$work/upgrade.log" 2>&1 \
  || { cat "$work/upgrade.log" >&2; fail "upgrade"; }
[ "$(sum)" = "$before" ] || fail "the upgrade changed the edited configuration or the trip record"
cmp -s "$root/etc/nori/supervisor.toml.dpkg-dist" "$work/config-next/supervisor.toml" \
  || fail "the new default is not left beside the kept file (supervisor.toml.dpkg-dist)"
[ "$(in_root dpkg-query -W -f '${Version}' nori-robot)" = "$next" ] || fail "not upgraded"
! grep -q "downgrading" "$work/upgrade.log" || fail "an upgrade called itself a downgrade"
[ ! -e "$root/etc/systemd/system/nori.target.wants/nori-lift.service" ] || fail "the upgrade enabled the lift again"
! grep -q '^[^#]*nori-lift' "$root/usr/lib/systemd/system/nori.target" || fail "nori.target pulls the lift in itself"
say "   kept byte for byte, the lift still disabled; nori-robot $next installed"

say "4. downgrade $next -> $n"
rm "$root/etc/nori/supervisor.toml.dpkg-dist"
in_root dpkg -i --force-confold "/debs/nori-robot_${n}_$arch.deb" "/debs/nori-sim_${n}_$arch.deb" >"$work/downgrade.log" 2>&1 \
  || { cat "$work/downgrade.log" >&2; fail "downgrade"; }
grep -q "kept: /var/lib/nori" "$work/downgrade.log" || fail "the downgrade did not say what it keeps"
[ "$(sum)" = "$before" ] || fail "the downgrade changed the edited configuration or the trip record"
say "   said what it keeps, and kept it"

say "5. from the fleet's repository: $n on stable, $next on beta"
repo=$work/repo
deploy/apt/repo.sh init "$repo"
deploy/apt/repo.sh publish "$repo" "$work"/n/*.deb
deploy/apt/repo.sh promote "$repo" "$n"
deploy/apt/repo.sh publish "$repo" "$work"/next/*.deb
port=$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
deploy/apt/repo.sh serve "$repo" "127.0.0.1:$port" 2>"$work/nginx.log" &
server=$!
python3 - "$port" <<'PY' || { cat "$work/nginx.log" >&2; fail "the repository is not served"; }
import sys, time, urllib.request as u
for _ in range(100):
    try:
        u.urlopen(f"http://127.0.0.1:{sys.argv[1]}/nori-archive-keyring.gpg", timeout=1); sys.exit(0)
    except OSError:
        time.sleep(0.1)
sys.exit(1)
PY
# As a robot is provisioned (deploy/README.md): the fleet's key, its channel, the stack held;
# no Debian mirror (the root's own is a snapshot here, and the check needs only the fleet's).
mv "$root/etc/apt/sources.list" "$work/debian.list"
cp "$repo/public/nori-archive-keyring.gpg" "$root/usr/share/keyrings/"
channel() { deploy/apt/repo.sh sources "http://127.0.0.1:$port" "$1" >"$root/etc/nori/fleet-repository.sources"; }
installed() { in_root dpkg-query -W -f '${Version}' nori-robot; }
upgrade() { in_root nori-upgrade "$@" >"$work/nori-upgrade.log" 2>&1; }
log() { cat "$work/nori-upgrade.log" "$work/nginx.log" >&2; }
in_root apt-mark hold nori-robot nori-sim >/dev/null
dists=$repo/public/dists
# HTTP dates are in seconds: a file put back within the second it was swapped would be taken
# for the one apt already refused (If-Modified-Since), so each swap back waits.
put_back() { sleep 1.1; rm -rf "$2"; cp -r "$1" "$2"; find "$2" -exec touch {} +; }

# A fresh robot on stable, served beta's index (signed by the same key) in stable's place.
cp -r "$dists/stable" "$work/stable"
rm -rf "$dists/stable" && cp -r "$dists/beta" "$dists/stable"
channel stable
if upgrade; then log; fail "an index signed for beta was taken for stable"; fi
grep -q "signed for beta: not upgrading" "$work/nori-upgrade.log" || { log; fail "no word of the channel's mix-up"; }
[ "$(installed)" = "$n" ] || fail "an index of another channel changed what is installed"
put_back "$work/stable" "$dists/stable"
upgrade --check || { log; fail "nori-upgrade --check on stable"; }
[ ! -s "$work/nori-upgrade.log" ] || { log; fail "stable holds $n, which is installed: nothing to do"; }
channel beta
upgrade --check || { log; fail "nori-upgrade --check on beta"; }
grep -q "would upgrade: nori-robot \[$n\] ($next nori:beta" "$work/nori-upgrade.log" || { log; fail "beta offers no $next"; }
say "   a fresh robot refuses beta's index served as stable; stable: nothing to do; beta: $next"

# An owner's plain apt, even with the fleet's source among apt's own: the stack is held.
cp "$root/etc/nori/fleet-repository.sources" "$root/etc/apt/sources.list.d/nori.sources"
in_root apt-get update -qq >"$work/apt.log" 2>&1 && in_root apt-get upgrade -y -q >>"$work/apt.log" 2>&1 \
  || { cat "$work/apt.log" >&2; fail "apt-get upgrade"; }
[ "$(installed)" = "$n" ] || fail "a plain apt-get upgrade moved the held stack"
rm "$root/etc/apt/sources.list.d/nori.sources"
say "   a plain apt-get upgrade leaves the held stack alone"

# Tampered on the way (or on the server): the channel's signed index, then a package.
index=$dists/beta/InRelease
cp -p "$index" "$work/InRelease"
sed -i 's/beta channel/other channel/' "$index"
if upgrade; then log; fail "an index whose signature fails was used"; fi
grep -q BADSIG "$work/nori-upgrade.log" || { log; fail "no word of the bad signature"; }
[ "$(installed)" = "$n" ] || fail "a tampered index changed what is installed"
sleep 1.1 && cp "$work/InRelease" "$index" && touch "$index"
deb=$(find "$repo/public/pool" -name "nori-robot_*${next}_$arch.deb")
cp -p "$deb" "$work/good.deb"
cp "$work"/n/nori-robot_*.deb "$deb"
in_root apt-get clean # nothing of beta fetched before, but no cache may hide the swap
if upgrade; then log; fail "a package that is not the one the index names was installed"; fi
grep -qi "hash sum mismatch\|unexpected size" "$work/nori-upgrade.log" || { log; fail "no word of the package's mismatch"; }
[ "$(installed)" = "$n" ] || fail "a tampered package changed what is installed"
cp "$work/good.deb" "$deb"
say "   a tampered index (BADSIG) and a tampered package (mismatch) refused; $n still installed"

upgrade || { log; fail "nori-upgrade from beta"; }
[ "$(installed)" = "$next" ] || fail "nori-upgrade did not install $next"
[ "$(cat "$root/usr/lib/nori/version")" = "$next" ] || fail "/usr/lib/nori/version does not say $next"
[ "$(sum)" = "$before" ] || fail "the upgrade from the repository changed the edited configuration or the trip record"
grep -q "review: /etc/nori/supervisor.toml is yours, kept" "$work/nori-upgrade.log" || { log; fail "the kept file with a new default is not named"; }
[ "$(in_root apt-mark showhold | sort | tr '\n' ' ')" = "nori-robot nori-sim " ] || fail "the stack is not held after the upgrade"
in_root nori up --dir /tmp/nori-up2 --domain "nori_debcheck2_$$" --run-for 8 >"$work/up2.log" 2>&1 \
  || { tail -30 "$work/up2.log" >&2; fail "nori up after the upgrade"; }
grep -qF "running nori-robot $next" "$work/up2.log" || { tail -30 "$work/up2.log" >&2; fail "the agent does not say it runs $next"; }
say "   upgraded to $next from beta, edits kept and the new default named, held; the packaged agent runs nori-robot $next"

say "every check passed ($arch)"
