#!/usr/bin/env bash
# Installs visnav on a companion computer: the binary, a configuration in /etc/visnav and the
# systemd unit visnav.service (docs/first-flight.md, "Deployment"). Run it from a checkout of the
# repository:
#
#   cargo build --release            # as your user (or --no-default-features: the flight build)
#   sudo scripts/install.sh          # as root: also creates the visnav user, enables the unit
#   scripts/install.sh --root DIR    # into DIR only (a staging tree or a board image): no user,
#                                    # no systemctl, says what it would do
#
# An existing /etc/visnav/visnav.toml is never overwritten: the new one goes beside it as
# visnav.toml.new. Files the configuration names by a relative path (relative to the
# configuration's folder) are copied into /etc/visnav so that they resolve there too.
set -euo pipefail

prog=install.sh
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"

usage() {
    cat <<EOF
Usage: scripts/install.sh [options]

Installs the visnav binary, a configuration and the systemd unit visnav.service.

  --root DIR      install under DIR (DESTDIR-style: DIR/usr/local/bin/visnav,
                  DIR/etc/visnav/visnav.toml, DIR/etc/systemd/system/visnav.service);
                  creates no user and runs no systemctl, prints what it would do
  --prefix DIR    installation prefix of the binary (default /usr/local: DIR/bin/visnav)
  --binary PATH   the binary to install (default target/release/visnav, built with
                  'cargo build --release' when absent)
  --config FILE   the configuration to install as /etc/visnav/visnav.toml
                  (default config/companion.toml); an existing one is kept and FILE is
                  installed beside it as visnav.toml.new
  --no-enable     do not enable visnav.service (it is enabled, not started, by default)
  -h, --help      this text

Without --root it must run as root: it creates the system user 'visnav' when missing,
runs 'systemctl daemon-reload' and 'systemctl enable visnav' (unless --no-enable), and
never starts the service.
EOF
}

die() {
    echo "$prog: error: $*" >&2
    exit 1
}

usage_error() {
    echo "$prog: $*" >&2
    echo "$prog: see '$0 --help'" >&2
    exit 2
}

root=""
prefix="/usr/local"
binary=""
config=""
enable=1

need_value() {
    # $1 option, $2 number of remaining arguments
    [ "$2" -ge 2 ] || usage_error "option $1 needs a value"
}

while [ $# -gt 0 ]; do
    case "$1" in
        --root) need_value "$1" $#; root="$2"; shift 2 ;;
        --root=*) root="${1#*=}"; shift ;;
        --prefix) need_value "$1" $#; prefix="$2"; shift 2 ;;
        --prefix=*) prefix="${1#*=}"; shift ;;
        --binary) need_value "$1" $#; binary="$2"; shift 2 ;;
        --binary=*) binary="${1#*=}"; shift ;;
        --config) need_value "$1" $#; config="$2"; shift 2 ;;
        --config=*) config="${1#*=}"; shift ;;
        --no-enable) enable=0; shift ;;
        -h | --help) usage; exit 0 ;;
        *) usage_error "unknown option '$1'" ;;
    esac
done

if [ -n "$root" ]; then
    [ -d "$root" ] || die "--root $root: no such directory"
    root="$(cd "$root" && pwd)"
    [ "$root" != / ] || root=""
    staged=1
else
    staged=0
fi
case "$prefix" in
    *[[:space:]]*) usage_error "--prefix '$prefix': no spaces, please (it goes into the unit's ExecStart)" ;;
    /*) prefix="${prefix%/}"; [ -n "$prefix" ] || prefix="/" ;;
    *) usage_error "--prefix $prefix: must be an absolute path" ;;
esac
if [ "$staged" = 0 ] && [ "$(id -u)" != 0 ]; then
    die "installing into the system needs root: run 'sudo $0 ...' (or --root DIR to install into a folder)"
fi

bindir="$prefix/bin"
[ "$prefix" != / ] || bindir=/bin
etc=/etc/visnav
conf="$etc/visnav.toml"
unitdir=/etc/systemd/system
unit="$unitdir/visnav.service"
logdir=/var/log/visnav
user=visnav
groups="dialout video"

say() { echo "$prog: $*"; }
warn() { echo "$prog: warning: $*" >&2; }

# --- the binary --------------------------------------------------------------------------------
if [ -z "$binary" ]; then
    target_dir="${CARGO_TARGET_DIR:-target}"
    case "$target_dir" in /*) ;; *) target_dir="$repo/$target_dir" ;; esac
    binary="$target_dir/release/visnav"
    if [ ! -e "$binary" ]; then
        command -v cargo >/dev/null 2>&1 \
            || die "no binary at $binary and cargo is not in PATH (sudo resets PATH): build it first as your user with 'cargo build --release', or give --binary PATH"
        say "no binary at $binary: building it (cargo build --release)"
        (cd "$repo" && cargo build --release --bin visnav) || die "cargo build --release failed"
    fi
fi
[ -f "$binary" ] || die "--binary $binary: no such file"
[ -x "$binary" ] || die "--binary $binary: not executable"
if version="$("$binary" --version 2>/dev/null)"; then
    say "binary: $binary ($version)"
else
    warn "$binary --version did not run here (built for another machine?); installing it anyway"
fi

# --- the configuration -------------------------------------------------------------------------
[ -n "$config" ] || config="$repo/config/companion.toml"
[ -f "$config" ] || die "--config $config: no such file"
[ -r "$config" ] || die "--config $config: not readable"
config_dir="$(cd "$(dirname "$config")" && pwd)"
config="$config_dir/$(basename "$config")"

# Every quoted string on the configuration's non-comment lines that names an existing file
# relative to the configuration's folder (the map's orthophotos, DEM, .vnm, a signing key, ...)
# is copied into /etc/visnav: to the same relative place when the path stays inside the folder,
# else beside the configuration (its name only) with the path in the installed copy rewritten.
declare -a copy_src=() copy_dst=() rewrite_from=() rewrite_to=()
while IFS= read -r token; do
    q="${token:0:1}"
    value="${token:1:${#token}-2}"
    case "$value" in "" | /* | *"{t}"*) continue ;; esac
    src="$config_dir/$value"
    if [ ! -f "$src" ]; then
        # Not a file here: say where visnav will look for what looks like a path.
        case "$value" in *[[:space:]]* | *:*) continue ;; esac
        if [ -d "$src" ]; then
            warn "$config names the folder \"$value\" (relative to its folder): not copied; put it at $etc/$value or give an absolute path"
        else
            case "$value" in
                */* | *.tif | *.tiff | *.vnm | *.key | *.y4m | *.csv)
                    warn "$config names \"$value\", which is not in $config_dir: visnav will look for it at $etc/$value (relative to the installed configuration); put it there or give an absolute path" ;;
            esac
        fi
        continue
    fi
    src="$(cd "$(dirname "$src")" && pwd)/$(basename "$src")"
    case "/$value/" in
        */../* | */./*) rel="$(basename "$value")" ;;
        *) rel="$value" ;;
    esac
    if [ "$rel" = "$(basename "$conf")" ] || [ "$rel" = "$(basename "$conf").new" ]; then
        die "$config names $value, whose installed name $etc/$rel would be the configuration itself: rename it"
    fi
    dup=0
    for i in "${!copy_dst[@]}"; do
        if [ "${copy_dst[$i]}" = "$rel" ]; then
            [ "${copy_src[$i]}" = "$src" ] \
                || die "$config names two files that would both be installed as $etc/$rel (${copy_src[$i]} and $src): rename one"
            dup=1
        fi
    done
    if [ "$dup" = 0 ]; then
        copy_src+=("$src")
        copy_dst+=("$rel")
    fi
    if [ "$rel" != "$value" ]; then
        rewrite_from+=("$q$value$q")
        rewrite_to+=("$q$rel$q")
    fi
done < <(grep -v '^[[:space:]]*#' "$config" | grep -oE "\"[^\"]*\"|'[^']*'" || true)

# Files the daemon writes, given relative: they would be written into /etc/visnav, which the
# unit keeps read-only.
while IFS= read -r line; do
    key="${line%%=*}"
    key="${key//[[:space:]]/}"
    val="${line#*=}"
    val="${val#"${val%%[![:space:]]*}"}"
    warn "$config: $key = $val: a relative path resolves to $etc, which the service cannot write: use an absolute path under $logdir"
done < <(grep -E "^[[:space:]]*(tlog|fix_log|vo_log)[[:space:]]*=[[:space:]]*[\"'][^/]" "$config" || true)

# --- the unit ----------------------------------------------------------------------------------
unit_text() {
    cat <<EOF
# visnav: vision-aided navigation for the autopilot (installed by scripts/install.sh).
# Change it with 'systemctl edit visnav' (a drop-in, kept across reinstalls), not here:
# scripts/install.sh rewrites this file.
[Unit]
Description=visnav vision-aided navigation (MAVLink to the autopilot)
# After the network when something on the system pulls network-online.target in; not pulled in
# here, so that a board without a network (in the field) does not wait for one at boot. A UDP
# link to another machine: add Wants=network-online.target in a drop-in.
After=network-online.target
# At most 30 starts in 10 minutes: starts that fail at once (every 5 s, e.g. the serial device
# is not there yet) are given up after about 2.5 minutes; then the unit stays failed until
# 'systemctl reset-failed visnav'.
StartLimitIntervalSec=600
StartLimitBurst=30

[Service]
Type=exec
ExecStart=$bindir/visnav run --config $conf
Restart=on-failure
RestartSec=5
# SIGTERM stops visnav cleanly (exit 0, no restart).
KillSignal=SIGTERM
TimeoutStopSec=15
# Logs: stderr (and stdout) to journald: journalctl -u visnav -f
StandardOutput=journal
StandardError=journal
SyslogIdentifier=visnav
# Environment=RUST_LOG=debug

# A dedicated system user; dialout owns the serial ports (/dev/ttyAMA*, ttyUSB*, ttyACM*,
# ttyTHS*), video the cameras (/dev/video*, /dev/media*).
User=$user
Group=$user
SupplementaryGroups=$groups
# /var/log/visnav, owned by $user: the flight records ([link] tlog, [daemon] fix_log, vo_log).
LogsDirectory=visnav
LogsDirectoryMode=0755

# Hardening that leaves the devices, UDP/TCP and the capture process alone: no PrivateDevices,
# DevicePolicy or ProtectClock (they close /dev/tty* and /dev/video*), no MemoryDenyWriteExecute
# or SystemCallFilter (GStreamer plugins run in the capture process).
NoNewPrivileges=yes
CapabilityBoundingSet=
AmbientCapabilities=
ProtectSystem=strict
ProtectHome=read-only
PrivateTmp=yes
ProtectKernelTunables=yes
ProtectKernelModules=yes
ProtectKernelLogs=yes
ProtectControlGroups=yes
ProtectHostname=yes
# AF_NETLINK: glibc's getaddrinfo (tcpout:HOST) and udev in capture programs use it.
RestrictAddressFamilies=AF_UNIX AF_INET AF_INET6 AF_NETLINK
RestrictNamespaces=yes
RestrictSUIDSGID=yes
LockPersonality=yes
SystemCallArchitectures=native

[Install]
WantedBy=multi-user.target
EOF
}

# --- install -----------------------------------------------------------------------------------
if [ "$staged" = 1 ]; then
    say "installing under ${root:-/} (--root: no user, no systemctl)"
fi

# $1 source, $2 destination (without root), $3 mode. Atomic: a running binary is replaced, not
# rewritten in place.
put() {
    local dst="$root$2"
    install -d -m 0755 "$(dirname "$dst")" || die "cannot create the folder $(dirname "$dst")"
    install -m "$3" "$1" "$dst.tmp.$$" || die "cannot write $dst.tmp.$$"
    mv -f "$dst.tmp.$$" "$dst" || die "cannot move $dst.tmp.$$ to $dst"
}

put "$binary" "$bindir/visnav" 0755
say "installed $binary -> $root$bindir/visnav"

# The configuration: a header naming its source, the rewritten relative paths.
tmp_conf="$(mktemp)"
trap 'rm -f "$tmp_conf"' EXIT
{
    echo "# Installed by scripts/install.sh from $config on $(date -u +%Y-%m-%d)."
    for i in "${!rewrite_from[@]}"; do
        echo "# ${rewrite_from[$i]} (relative to $config_dir) is ${rewrite_to[$i]} here (copied beside this file)."
    done
    if [ ${#rewrite_from[@]} -eq 0 ]; then
        cat "$config"
    else
        # Literal replacement of each quoted path (index/substr: no regular expressions).
        for i in "${!rewrite_from[@]}"; do
            export "VISNAV_FROM_$i=${rewrite_from[$i]}" "VISNAV_TO_$i=${rewrite_to[$i]}"
        done
        VISNAV_N="${#rewrite_from[@]}" awk '
            BEGIN { n = ENVIRON["VISNAV_N"] + 0
                    for (i = 0; i < n; i++) { from[i] = ENVIRON["VISNAV_FROM_" i]; to[i] = ENVIRON["VISNAV_TO_" i] } }
            /^[ \t]*#/ { print; next }
            {
                line = $0
                for (i = 0; i < n; i++) {
                    out = ""
                    while ((p = index(line, from[i])) > 0) {
                        out = out substr(line, 1, p - 1) to[i]
                        line = substr(line, p + length(from[i]))
                    }
                    line = out line
                }
                print line
            }' "$config"
    fi
} >"$tmp_conf" || die "cannot prepare the configuration from $config"

install -d -m 0755 "$root$etc" || die "cannot create the folder $root$etc"
conf_written="$conf"
if [ -e "$root$conf" ]; then
    if cmp -s <(grep -v '^# Installed by scripts/install.sh' "$tmp_conf") \
        <(grep -v '^# Installed by scripts/install.sh' "$root$conf"); then
        say "$root$conf is already this configuration: unchanged"
        conf_written=""
    else
        conf_written="$conf.new"
        put "$tmp_conf" "$conf_written" 0644
        say "$root$conf exists and is kept: the new configuration is $root$conf_written (compare: diff $root$conf $root$conf_written)"
    fi
else
    put "$tmp_conf" "$conf" 0644
    say "installed $config -> $root$conf"
fi

# The files the configuration names by a relative path; never overwritten either.
for i in "${!copy_src[@]}"; do
    src="${copy_src[$i]}"
    dst="$etc/${copy_dst[$i]}"
    if [ -e "$root$dst" ]; then
        if cmp -s "$src" "$root$dst"; then
            say "$root$dst is already installed"
        else
            warn "$root$dst exists and differs from $src: kept (the configuration names it; copy it by hand if you want the new one)"
        fi
    else
        put "$src" "$dst" 0644
        say "installed $src -> $root$dst (named in the configuration)"
    fi
done
if [ ${#copy_src[@]} -gt 0 ]; then
    for i in "${!copy_src[@]}"; do
        case "${copy_dst[$i]}" in
            *.vnm) say "note: the DEM a .vnm map names is loaded from beside it or from its recorded path: copy it to $root$etc/$(dirname "${copy_dst[$i]}") too, or set [map] dem" ;;
        esac
    done
fi

# The unit (ours: replaced; an edited one is kept as .old).
tmp_unit="$(mktemp)"
trap 'rm -f "$tmp_conf" "$tmp_unit"' EXIT
unit_text >"$tmp_unit"
if [ -e "$root$unit" ] && ! cmp -s "$tmp_unit" "$root$unit"; then
    cp -p "$root$unit" "$root$unit.old" || die "cannot save $root$unit as $root$unit.old"
    say "$root$unit differed from this installer's: the old one is $root$unit.old (use 'systemctl edit visnav' for changes)"
fi
put "$tmp_unit" "$unit" 0644
say "installed the unit $root$unit (ExecStart=$bindir/visnav run --config $conf, User=$user)"

# The flight records' folder (the unit's LogsDirectory creates it too, at the first start; it
# must exist before for 'visnav check-config').
if [ "$staged" = 1 ]; then
    install -d -m 0755 "$root$logdir" || die "cannot create the folder $root$logdir"
    say "created $root$logdir (would be owned by $user)"
    say "would run: useradd --system --user-group --no-create-home --home-dir /nonexistent --shell /usr/sbin/nologin --groups ${groups// /,} $user (if missing)"
    say "would run: systemctl daemon-reload"
    if [ "$enable" = 1 ]; then
        say "would run: systemctl enable visnav.service (not started)"
    fi
    exit 0
fi

for g in $groups; do
    getent group "$g" >/dev/null || die "the group '$g' does not exist on this system, but the unit's SupplementaryGroups needs it: create it (groupadd --system $g) or edit $unit"
done
if ! getent passwd "$user" >/dev/null; then
    command -v useradd >/dev/null 2>&1 || die "useradd not found: create the system user '$user' by hand"
    useradd --system --user-group --no-create-home --home-dir /nonexistent \
        --shell /usr/sbin/nologin --groups "${groups// /,}" "$user" \
        || die "could not create the system user '$user'"
    say "created the system user '$user' (groups: $groups)"
else
    say "the user '$user' exists"
fi
install -d -m 0755 -o "$user" -g "$user" "$logdir" || die "cannot create the folder $logdir"
say "$logdir is owned by $user"

command -v systemctl >/dev/null 2>&1 || die "systemctl not found: this installer needs systemd (or use --root DIR and your own supervisor)"
# systemd running (sd_booted): reload it; in a chroot or a container without it, enabling still
# works (symlinks) and the unit is read at the next boot.
if [ -d /run/systemd/system ]; then
    systemctl daemon-reload || die "systemctl daemon-reload failed"
    say "ran systemctl daemon-reload"
    booted=1
else
    say "systemd is not running here: no daemon-reload (the unit is read at the next boot)"
    booted=0
fi
if [ "$enable" = 1 ]; then
    systemctl enable visnav.service || die "systemctl enable visnav.service failed"
    say "enabled visnav.service (starts at boot; not started now)"
fi
if [ "$booted" = 1 ] && systemctl is-active --quiet visnav.service; then
    say "visnav.service is running the old binary: 'systemctl restart visnav' to use the new one"
fi

# The configuration the service runs, checked as the service's user sees it.
checked="$conf"
say "visnav check-config $checked (as $user):"
if command -v runuser >/dev/null 2>&1; then
    run_as=(runuser -u "$user" --)
else
    run_as=()
fi
"${run_as[@]}" "$bindir/visnav" check-config "$checked" || warn "the configuration does not pass yet: see above"

echo
echo "Next steps:"
if [ "$conf_written" = "$conf.new" ]; then
    echo "  0. Compare:            diff $conf $conf.new"
    echo "     take what you want from the new one into $conf, then delete $conf.new"
fi
cat <<EOF
  1. Edit $conf (docs/first-flight.md):
     [link] connection: the serial port wired to the autopilot's TELEM port; [camera] and
     [frames]: your camera; [map]: your map; [output]: what your autopilot takes
  2. Check it:            sudo -u $user $bindir/visnav check-config $conf
  3. Start the service:   sudo systemctl start visnav
  4. Follow its log:      journalctl -u visnav -f
EOF
