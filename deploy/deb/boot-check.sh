#!/usr/bin/env bash
# nori-robot's maintainer scripts where they matter: on a booted systemd, with the stack running.
# (deploy/deb/check.sh installs into a chroot, where no systemd runs, so every step that stops,
# orders and starts the units is skipped there.)
#
#   deploy/deb/boot-check.sh BIN_DIR
#
# builds version N and N+1 of the packages from BIN_DIR's amd64 binaries (target/tested or
# target/release), puts them and deploy/deb/boot-guest.sh into a bookworm root with a kernel,
# boots it under qemu-system-x86_64 (KVM when /dev/kvm opens, else emulated) and reads what the
# guest script reports on a second serial port. What the guest checks: boot-guest.sh.
#
#   deploy/deb/boot-check.sh --prepare
#
# only fetches the host's tools (qemu-system-x86, seabios, debootstrap, e2fsprogs) and the
# pristine root, cached in $NORI_DEB_CHECK_CACHE (/var/tmp/nori-deb-check). Needs root.
set -euo pipefail
cd "$(dirname "$0")/../.."
usage() { sed -n '2,17p' "$0" | sed 's/^# \{0,1\}//' >&2; exit 2; }
[ $# -eq 1 ] || usage
cache=${NORI_DEB_CHECK_CACHE:-/var/tmp/nori-deb-check}
mirror=${NORI_DEBIAN_MIRROR:-http://deb.debian.org/debian}
pristine=$cache/bookworm-amd64-booted.tar
say() { echo "boot-check: $*" >&2; }
fail() { echo "boot-check: FAILED: $*" >&2; exit 1; }

prepare() {
  local tools=()
  command -v qemu-system-x86_64 >/dev/null || tools+=(qemu-system-x86)
  [ -e /usr/share/seabios/bios-256k.bin ] || tools+=(seabios)
  command -v debootstrap >/dev/null || tools+=(debootstrap)
  command -v mkfs.ext4 >/dev/null || tools+=(e2fsprogs)
  if ((${#tools[@]})); then
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${tools[@]}" >/dev/null
  fi
  [ ! -s "$pristine" ] || return 0
  say "debootstrap bookworm amd64 with a kernel (once; cached in $pristine)"
  tmp=$(mktemp -d)
  trap 'rm -rf "$tmp"' EXIT
  debootstrap --variant=minbase --include=systemd,udev,initramfs-tools,linux-image-cloud-amd64 \
    bookworm "$tmp" "$mirror" >/dev/null
  # The kernel must mount a virtio disk holding ext4: the drivers in the initramfs (MODULES=most)
  # or built in.
  local modules
  modules=$(chroot "$tmp" sh -c 'lsinitramfs /boot/initrd.img-*')
  for m in VIRTIO_PCI:virtio_pci VIRTIO_BLK:virtio_blk EXT4_FS:ext4; do
    grep -qx "CONFIG_${m%:*}=y" "$tmp"/boot/config-* || grep -q "/${m#*:}.ko" <<<"$modules" \
      || fail "the root's kernel cannot mount its disk: no ${m#*:}"
  done
  mkdir -p "$cache" && tar -C "$tmp" -cf "$pristine.part" . && mv "$pristine.part" "$pristine"
  rm -rf "$tmp"
  trap - EXIT
}
if [ "$1" = --prepare ]; then
  prepare
  exit
fi
bin_dir=$1
prepare

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
root=$work/root
mkdir "$root" && tar -C "$root" -xf "$pristine"
chmod 755 "$root"
# shellcheck source=deploy/deb/two-versions.sh
. deploy/deb/two-versions.sh
build_two_versions amd64 "$bin_dir" "$work"
mkdir "$root/debs" && cp "$work"/n/*.deb "$work"/next/*.deb deploy/config/calibration.toml "$root/debs/"
echo "$n $next" >"$root/debs/versions"
install -m 755 deploy/deb/boot-guest.sh "$root/usr/local/sbin/nori-boot-check"

# The guest's test: a oneshot after the boot is done, reporting on ttyS1, powering off either
# way. Its names stay out of `nori-*`: the maintainer scripts stop and restart what matches.
cat >"$root/etc/systemd/system/boot-check.service" <<'EOF'
[Unit]
Description=nori-robot's maintainer scripts on a booted systemd
After=multi-user.target
SuccessAction=poweroff-force
FailureAction=poweroff-force
[Service]
Type=oneshot
ExecStart=/usr/local/sbin/nori-boot-check
StandardOutput=tty
StandardError=tty
TTYPath=/dev/ttyS1
TimeoutStartSec=50min
EOF
cat >"$root/etc/systemd/system/boot-check.target" <<'EOF'
[Unit]
Description=Boot, then check nori-robot's maintainer scripts
Requires=multi-user.target boot-check.service
After=multi-user.target
AllowIsolate=yes
EOF

img=$work/root.img
truncate -s "$(($(du -sm "$root" | cut -f1) + 1024))M" "$img"
# -d keeps each file's owner and mode; no loop device is needed.
mkfs.ext4 -q -F -d "$root" "$img"
rm -rf "$root/debs"

# -smp 4: the driver's unit pins it to CPU 3 and the supervisor's to CPU 2. KVM needs the
# CPU's own virtualisation (kvm_intel or kvm_amd): the kvm_pvm of a nested machine (this one)
# opens /dev/kvm but hangs or fails emulating a stock kernel's start.
if [ -w /dev/kvm ] && { [ -d /sys/module/kvm_intel ] || [ -d /sys/module/kvm_amd ]; }; then
  accel=(-accel kvm) limit=600
else
  accel=(-accel tcg,thread=multi) limit=3600
fi
say "booting (${accel[1]%%,*}, at most $limit s)"
start=$SECONDS
kernel=$(ls "$root"/boot/vmlinuz-*) initrd=$(ls "$root"/boot/initrd.img-*)
rc=0
timeout --foreground -k 10 "$limit" qemu-system-x86_64 "${accel[@]}" -cpu max -machine q35 -smp 4 -m 2G \
  -L /usr/share/seabios -L /usr/share/qemu -nodefaults -display none -no-reboot -nic none \
  -device virtio-rng-pci -drive "file=$img,if=virtio,format=raw,cache=unsafe" \
  -kernel "$kernel" -initrd "$initrd" \
  -append "root=/dev/vda rw console=ttyS0,115200 init=/lib/systemd/systemd panic=-1 systemd.unit=boot-check.target systemd.mask=serial-getty@ttyS0.service" \
  -serial "file:$work/console.log" -serial "file:$work/result.log" </dev/null || rc=$?
cat "$work/result.log" >&2 || true
if [ $rc != 0 ] || ! grep -q "^NORI-BOOT-CHECK: PASS" "$work/result.log"; then
  say "qemu exited $rc after $((SECONDS - start)) s; the console's end:"
  tail -40 "$work/console.log" >&2
  fail "on a booted systemd"
fi
say "every check passed on a booted systemd ($((SECONDS - start)) s)"
