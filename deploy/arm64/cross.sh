#!/usr/bin/env bash
# The robot's own computer from this one: every robot binary built for aarch64 (Raspberry Pi 5)
# and the robot crates' tests run as arm64 processes under qemu user mode, from Debian's archive
# only (rustup cannot fetch other targets here).
#
#   deploy/arm64/cross.sh root    make (or update) the build root: a Debian sid chroot with
#                                 Debian's rustc/cargo, libstd-rust-dev:arm64, the aarch64 gcc,
#                                 libclang (the cameras' V4L2 bindings) and qemu-user
#   deploy/arm64/cross.sh build   the robot's and the simulator's binaries for aarch64; prints
#                                 each one's size and the glibc it needs, and fails if one needs
#                                 more than the oldest supported Raspberry Pi OS has
#   deploy/arm64/cross.sh test [unit|process|both [FILTER]]
#                                 the robot crates' unit tests and the process tests that matter
#                                 most on the Pi, as arm64 processes (timings are not taken);
#                                 both unless one is named; FILTER: only the tests whose names
#                                 contain it (as cargo test's)
#   deploy/arm64/cross.sh all     the three in turn
#
# The root lives in $NORI_CROSS_ROOT (/var/tmp/nori-cross/root); the sources are the working
# tree's tracked and new files, copied in (so a build uses exactly what git sees, with
# Cargo.lock, --locked); the build output stays in the root (/build/target) between runs and the
# binaries are copied out to target/aarch64-unknown-linux-gnu/release/. Needs root (chroot,
# mounts, binfmt_misc). The figures of a run: BENCHMARKS.md, "arm64".
set -euo pipefail
cd "$(dirname "$0")/../.."
repo=$(pwd)
root=${NORI_CROSS_ROOT:-/var/tmp/nori-cross/root}
mirror=${NORI_DEBIAN_MIRROR:-http://deb.debian.org/debian}
target=aarch64-unknown-linux-gnu

# Raspberry Pi OS bookworm (Debian 12) has glibc 2.36; trixie 2.41. bookworm is what most Pi 5s
# in the field run, so it is the oldest supported, and no binary may need more.
oldest_glibc=2.36
oldest_os="Raspberry Pi OS bookworm"

# shellcheck source=deploy/binaries.sh
. deploy/binaries.sh
# The crates whose binaries those are.
packages=(-p bus-driver -p supervisor -p fleet-agent -p camera -p lidar -p base -p lift
  -p recorder -p blackbox -p nori -p sim -p stack)
unit_tested=(feetech telemetry bus-driver supervisor fleet-agent base lift camera lidar recorder blackbox body)
process_tests=(stack_on_sim latch crash_isolation heartbeats thermal_ordering)

say() { echo "cross: $*" >&2; }

make_root() {
  if [ ! -x "$root/usr/bin/apt-get" ]; then
    command -v debootstrap >/dev/null || { apt-get update -qq && apt-get install -y -qq debootstrap; }
    say "debootstrap sid into $root"
    mkdir -p "$root"
    debootstrap --variant=minbase sid "$root" "$mirror" >/dev/null
  fi
  cp /etc/resolv.conf "$root/etc/resolv.conf"
  # The certificate authorities this machine trusts beyond Debian's (a site's egress proxy).
  mkdir -p "$root/usr/local/share/ca-certificates"
  cp /usr/local/share/ca-certificates/*.crt "$root/usr/local/share/ca-certificates/" 2>/dev/null || true
  # The archive mirrored here may be a snapshot whose Release file has expired.
  echo 'Acquire::Check-Valid-Until "false";' >"$root/etc/apt/apt.conf.d/99nori-snapshot"
  in_root sh -c 'dpkg --add-architecture arm64 && apt-get update -qq &&
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
      rustc cargo libstd-rust-dev:arm64 gcc-aarch64-linux-gnu libc6-dev:arm64 \
      linux-libc-dev:arm64 libclang-dev qemu-user pkg-config binutils ca-certificates >/dev/null &&
    update-ca-certificates >/dev/null'
  make_sysroot
  in_root sh -c 'rustc --version; cargo --version; aarch64-linux-gnu-gcc --version | head -1;
    qemu-aarch64 --version | head -1; dpkg-query -W libc6:arm64' | sed 's/^/cross: root has /' >&2
}

# The binaries link against bookworm's glibc, not sid's: a symbol sid's glibc added that std
# references weakly (pidfd_spawnp, GLIBC_2.39) would otherwise become a hard version need, and
# the binary would not start on bookworm. Linked against bookworm's libc.so the weak symbol stays
# unversioned and std falls back at run time. C code (ring) and the V4L2 bindings see bookworm's
# headers too.
sysroot=/sysroot-bookworm
make_sysroot() {
  echo "deb [arch=arm64] $mirror bookworm main" >"$root/etc/apt/sources.list.d/nori-bookworm-arm64.list"
  in_root sh -c "apt-get update -qq && rm -rf $sysroot /tmp/sysroot-debs && mkdir -p $sysroot /tmp/sysroot-debs &&
    cd /tmp/sysroot-debs && apt-get download -qq libc6:arm64/bookworm libc6-dev:arm64/bookworm \
      linux-libc-dev:arm64/bookworm libgcc-s1:arm64/bookworm &&
    for d in *.deb; do dpkg-deb -x \$d $sysroot; done && ls *.deb"
  printf '#!/bin/sh\nexec aarch64-linux-gnu-gcc --sysroot=%s "$@"\n' "$sysroot" >"$root/usr/local/bin/nori-aarch64-cc"
  chmod 755 "$root/usr/local/bin/nori-aarch64-cc"
}

mounted=()
mount_root() {
  for m in proc dev dev/pts; do
    if ! mountpoint -q "$root/$m"; then
      case $m in
        proc) mount -t proc proc "$root/proc" ;;
        *) mount --bind "/$m" "$root/$m" ;;
      esac
      mounted=("$root/$m" "${mounted[@]}")
    fi
  done
}
unmount_root() {
  for m in "${mounted[@]}"; do umount "$m" || true; done
}
trap unmount_root EXIT

in_root() {
  mount_root
  chroot "$root" env -i HOME=/root PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin LANG=C.UTF-8 \
    CARGO_HOME=/build/cargo-home CARGO_TARGET_DIR=/build/target CARGO_INCREMENTAL=0 \
    CARGO_BUILD_TARGET=$target \
    CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_LINKER=nori-aarch64-cc \
    CC_aarch64_unknown_linux_gnu=nori-aarch64-cc \
    BINDGEN_EXTRA_CLANG_ARGS_aarch64_unknown_linux_gnu="--sysroot=$sysroot" \
    AR_aarch64_unknown_linux_gnu=aarch64-linux-gnu-ar \
    SOURCE_DATE_EPOCH="$(git -C "$repo" log -1 --format=%ct)" \
    RUSTFLAGS="--remap-path-prefix=/build/src=. --remap-path-prefix=/build/cargo-home=~/.cargo" \
    CI="${CI:-}" NORI_SKIP_SLOW="${NORI_SKIP_SLOW:-}" "$@"
}

# arm64 executables run through qemu: the kernel hands them to qemu-aarch64 (the root's, static),
# which is opened once here (flag F) so it serves inside and outside the chroot.
register_qemu() {
  local reg=/proc/sys/fs/binfmt_misc
  mountpoint -q $reg || mount -t binfmt_misc binfmt_misc $reg
  [ -e $reg/nori-aarch64 ] && return
  printf '%s' ':nori-aarch64:M::\x7fELF\x02\x01\x01\x00\x00\x00\x00\x00\x00\x00\x00\x00\x02\x00\xb7\x00:\xff\xff\xff\xff\xff\xff\xff\x00\xff\xff\xff\xff\xff\xff\xff\xff\xfe\xff\xff\xff:'"$root"'/usr/bin/qemu-aarch64:F' >$reg/register
}

copy_sources() {
  say "copying the working tree's files into the root"
  rm -rf "$root/build/src" && mkdir -p "$root/build/src"
  git -C "$repo" ls-files -z --cached --others --exclude-standard \
    | (cd "$repo" && tar --null -T - -cf -) | tar -xf - -C "$root/build/src"
}

# Every GLIBC_x.y a binary asks for, newest last.
glibc_needs() {
  in_root aarch64-linux-gnu-objdump -T "$1" | grep -o 'GLIBC_[0-9.]*' | sed 's/GLIBC_//' | sort -uV
}

build() {
  copy_sources
  say "building ${#robot_bins[@]} robot and ${#sim_bins[@]} simulator binaries for $target"
  local start=$SECONDS
  in_root sh -c "cd /build/src && cargo build --locked --release --bins ${packages[*]}"
  say "built in $((SECONDS - start)) s"
  local out="$repo/target/$target/release" failed=0
  mkdir -p "$out"
  printf '%-14s %10s  %-8s %s\n' binary bytes glibc "arch" >&2
  for b in "${robot_bins[@]}" "${sim_bins[@]}"; do
    local f=/build/target/$target/release/$b
    cp "$root$f" "$out/$b"
    local newest arch
    newest=$(glibc_needs "$f" | tail -1)
    arch=$(in_root aarch64-linux-gnu-readelf -h "$f" | sed -n 's/ *Machine: *//p')
    printf '%-14s %10d  %-8s %s\n' "$b" "$(stat -c %s "$out/$b")" "$newest" "$arch" >&2
    if [ "$(printf '%s\n%s\n' "$newest" "$oldest_glibc" | sort -V | tail -1)" != "$oldest_glibc" ]; then
      say "$b needs glibc $newest; $oldest_os has $oldest_glibc"
      failed=1
    fi
  done
  [ $failed = 0 ] || exit 1
  say "every binary runs on $oldest_os (glibc $oldest_glibc) or later"
}

run_tests() {
  local which=${1:-both} filter=${2:-}
  case $which in both | unit | process) ;; *) say "test: unit, process or neither (both)"; exit 2 ;; esac
  register_qemu
  copy_sources
  if [ "$which" != process ]; then
    local args=()
    for c in "${unit_tested[@]}"; do args+=(-p "$c"); done
    say "unit tests of ${unit_tested[*]} as arm64 processes"
    in_root sh -c "cd /build/src && cargo test --locked --release ${args[*]} --lib --bins -- $filter"
  fi
  if [ "$which" != unit ]; then
    local tests=()
    for t in "${process_tests[@]}"; do tests+=(--test "$t"); done
    say "process tests ${process_tests[*]} as arm64 processes"
    # NORI_EMULATED: the tests hold their invariants and report, not bound, their timings.
    in_root sh -c "cd /build/src && NORI_EMULATED=qemu-aarch64 cargo test --locked --release --no-fail-fast -p nori-tests ${tests[*]} -- $filter"
  fi
  say "every test above ran as an arm64 process under qemu-aarch64"
}

case "${1:-}" in
  root) make_root ;;
  build) build ;;
  test) run_tests "${2:-both}" "${3:-}" ;;
  all) make_root && build && run_tests ;;
  *) sed -n '2,17p' "$0" | sed 's/^# \{0,1\}//' >&2; exit 2 ;;
esac
