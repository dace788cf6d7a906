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
#   4. N is installed over N+1 (a downgrade): it says what it keeps, and keeps it.
# Needs root (debootstrap, chroot, mounts). The pristine root is cached in
# $NORI_DEB_CHECK_CACHE (/var/tmp/nori-deb-check); each run starts from a fresh copy.
set -euo pipefail
cd "$(dirname "$0")/../.."
[ $# -eq 2 ] || { sed -n '2,17p' "$0" | sed 's/^# \{0,1\}//' >&2; exit 2; }
arch=$1 bin_dir=$2
cache=${NORI_DEB_CHECK_CACHE:-/var/tmp/nori-deb-check}
mirror=${NORI_DEBIAN_MIRROR:-http://deb.debian.org/debian}
say() { echo "deb-check: $*" >&2; }
fail() { echo "deb-check: FAILED: $*" >&2; exit 1; }

pristine=$cache/bookworm-$arch.tar
if [ ! -s "$pristine" ]; then
  command -v debootstrap >/dev/null || { apt-get update -qq && apt-get install -y -qq debootstrap; }
  say "debootstrap bookworm $arch (once; cached in $pristine)"
  tmp=$(mktemp -d)
  debootstrap --variant=minbase --arch="$arch" --include=systemd,udev bookworm "$tmp" "$mirror" >/dev/null
  mkdir -p "$cache" && tar -C "$tmp" -cf "$pristine" . && rm -rf "$tmp"
fi

work=$(mktemp -d)
root=$work/root
mounts=()
cleanup() {
  for m in "${mounts[@]}"; do umount "$m" 2>/dev/null || true; done
  rm -rf "$work"
}
trap cleanup EXIT
mkdir "$root" && tar -C "$root" -xf "$pristine"
for m in proc dev dev/pts; do
  case $m in proc) mount -t proc proc "$root/proc" ;; *) mount --bind "/$m" "$root/$m" ;; esac
  mounts=("$root/$m" "${mounts[@]}")
done
in_root() { chroot "$root" env -i PATH=/usr/sbin:/usr/bin:/sbin:/bin HOME=/root LANG=C.UTF-8 "$@"; }

n=0.1.0+$(git rev-list --count HEAD)
next=$n.1
export NORI_DEB_COMPRESSION=${NORI_DEB_COMPRESSION:-gzip}
deploy/deb/build.sh "$arch" "$bin_dir" "$work/n" "$n"
deploy/deb/build.sh "$arch" "$bin_dir" "$work/next" "$next"
mkdir "$root/debs" && cp "$work"/n/*.deb "$work"/next/*.deb "$root/debs/"

say "0. lintian"
command -v lintian >/dev/null || { apt-get update -qq && apt-get install -y -qq lintian >/dev/null; }
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
for u in nori-supervisor nori-bus-driver nori-fleet-agent nori-lidar nori-base nori-lift \
  nori-camera@head nori-camera@neck nori-camera@left_wrist nori-camera@right_wrist; do
  [ -L "$root/etc/systemd/system/nori.target.wants/$u.service" ] || fail "$u not enabled"
done
[ -L "$root/etc/systemd/system/multi-user.target.wants/nori.target" ] || fail "nori.target not enabled"
in_root sh -c 'cd /usr/lib/systemd/system && cp nori-camera@.service /tmp/nori-camera@head.service &&
  systemd-analyze verify --man=no nori-supervisor.service nori-bus-driver.service \
    nori-fleet-agent.service nori-lidar.service nori-base.service nori-lift.service \
    /tmp/nori-camera@head.service nori.target' >"$work/verify.log" 2>&1 \
  || { cat "$work/verify.log" >&2; fail "systemd-analyze verify"; }
# It exits 0 on a key it ignores, but names the unit: ours must draw no word at all.
if grep -i nori "$work/verify.log" >&2; then fail "systemd-analyze verify"; fi
say "   installed: the user, /var/lib/nori, 11 units enabled and verified"

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
in_root dpkg -i "/debs/nori-robot_${next}_$arch.deb" "/debs/nori-sim_${next}_$arch.deb" >"$work/upgrade.log" 2>&1 \
  || { cat "$work/upgrade.log" >&2; fail "upgrade"; }
[ "$(sum)" = "$before" ] || fail "the upgrade changed the edited configuration or the trip record"
[ "$(in_root dpkg-query -W -f '${Version}' nori-robot)" = "$next" ] || fail "not upgraded"
! grep -q "downgrading" "$work/upgrade.log" || fail "an upgrade called itself a downgrade"
[ ! -e "$root/etc/systemd/system/nori.target.wants/nori-lift.service" ] || fail "the upgrade enabled the lift again"
! grep -q '^[^#]*nori-lift' "$root/usr/lib/systemd/system/nori.target" || fail "nori.target pulls the lift in itself"
say "   kept byte for byte, the lift still disabled; nori-robot $next installed"

say "4. downgrade $next -> $n"
in_root dpkg -i "/debs/nori-robot_${n}_$arch.deb" "/debs/nori-sim_${n}_$arch.deb" >"$work/downgrade.log" 2>&1 \
  || { cat "$work/downgrade.log" >&2; fail "downgrade"; }
grep -q "kept: /var/lib/nori" "$work/downgrade.log" || fail "the downgrade did not say what it keeps"
[ "$(sum)" = "$before" ] || fail "the downgrade changed the edited configuration or the trip record"
say "   said what it keeps, and kept it"
say "every check passed ($arch)"
