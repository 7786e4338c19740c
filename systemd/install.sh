#!/usr/bin/env bash
# Install the companion daemon as a systemd service (Raspberry Pi OS bookworm, Debian 12).
#
#   sudo systemd/install.sh [--source DIR] [--dry-run]
#
# Steps: system user "companion" (groups dialout, video); a venv in /opt/companion/venv (PEP 668
# forbids pip in the system Python) with the project pip-installed from the source tree; the
# example config copied to /etc/companion/companion.yaml unless that file exists; the unit in
# /etc/systemd/system; daemon-reload; enable and (re)start. Safe to re-run for an upgrade.
# --dry-run prints the commands instead of running them and needs no root.
set -euo pipefail

readonly SERVICE_USER=companion
readonly PREFIX=/opt/companion
readonly VENV="$PREFIX/venv"
readonly CONF_DIR=/etc/companion
readonly CONF_FILE="$CONF_DIR/companion.yaml"
readonly UNIT_DIR=/etc/systemd/system
readonly UNIT_NAME=companion.service
readonly EXAMPLE_CONFIG=config/example-ardupilot-hokuyo.yaml

usage() {
    cat <<EOF
Usage: $0 [--source DIR] [--dry-run]

Install the companion daemon as the systemd service $UNIT_NAME (run as root).

  --source DIR  project source tree to install (default: the repository holding this script)
  --dry-run     print the commands instead of running them (no root needed)
  -h, --help    show this help
EOF
}

die() {
    printf 'install.sh: error: %s\n' "$*" >&2
    exit 1
}

note() {
    printf '==> %s\n' "$*"
}

# Run a command, or only print it with --dry-run (arguments quoted where the shell needs it).
run() {
    if ((DRY_RUN)); then
        local arg line='+'
        for arg in "$@"; do
            if [[ "$arg" =~ ^[[:alnum:]_./,:=@%+-]+$ ]]; then
                line+=" $arg"
            else
                line+=" $(printf '%q' "$arg")"
            fi
        done
        printf '%s\n' "$line"
    else
        "$@"
    fi
}

DRY_RUN=0
SRC_DIR="$(cd -- "$(dirname -- "${BASH_SOURCE[0]}")/.." && pwd)"

while (($#)); do
    case "$1" in
        --dry-run) DRY_RUN=1 ;;
        --source)
            (($# >= 2)) || die "--source needs a directory"
            SRC_DIR="$2"
            shift
            ;;
        --source=*) SRC_DIR="${1#--source=}" ;;
        -h | --help)
            usage
            exit 0
            ;;
        *)
            usage >&2
            die "unknown argument: $1"
            ;;
    esac
    shift
done

if ((EUID != 0 && !DRY_RUN)); then
    die "must be run as root (try: sudo $0), or use --dry-run"
fi

[[ -d "$SRC_DIR" ]] || die "source directory not found: $SRC_DIR"
SRC_DIR="$(cd -- "$SRC_DIR" && pwd)"
for required in pyproject.toml "systemd/$UNIT_NAME" "$EXAMPLE_CONFIG"; do
    [[ -f "$SRC_DIR/$required" ]] ||
        die "$SRC_DIR/$required not found: is this the companion source tree?"
done
command -v python3 >/dev/null || die "python3 not found (apt install python3 python3-venv)"
python3 -c 'import sys; sys.exit(sys.version_info < (3, 11))' ||
    die "Python >= 3.11 required, found $(python3 -V 2>&1)"
if ((DRY_RUN)); then
    note "dry run: printing the commands, changing nothing"
else
    command -v systemctl >/dev/null || die "systemctl not found: this script needs systemd"
fi

note "service user $SERVICE_USER"
if ! getent group "$SERVICE_USER" >/dev/null; then
    run groupadd --system "$SERVICE_USER"
fi
if id -u "$SERVICE_USER" >/dev/null 2>&1; then
    run usermod --append --groups dialout,video "$SERVICE_USER"
else
    run useradd --system --gid "$SERVICE_USER" --groups dialout,video \
        --home-dir "/var/lib/$SERVICE_USER" --no-create-home \
        --shell /usr/sbin/nologin --comment "UAV navigation companion" "$SERVICE_USER"
fi

note "virtual environment $VENV"
run install -d -m 0755 "$PREFIX"
if [[ ! -x "$VENV/bin/python" ]]; then
    # Debian ships venv's pip bootstrap (ensurepip) in a separate package.
    if ! python3 -c 'import ensurepip' >/dev/null 2>&1; then
        run apt-get install --yes python3-venv
    fi
    run python3 -m venv "$VENV"
fi
# Not editable: the service runs what was installed, whatever happens to the source tree.
run "$VENV/bin/python" -m pip install --upgrade "$SRC_DIR"

note "configuration $CONF_FILE"
run install -d -m 0755 "$CONF_DIR"
if [[ -e "$CONF_FILE" ]]; then
    note "keeping the existing $CONF_FILE"
else
    # Group-readable by the service only: the config may hold network keys.
    run install -m 0640 -o root -g "$SERVICE_USER" "$SRC_DIR/$EXAMPLE_CONFIG" "$CONF_FILE"
fi
if [[ ! -e "$CONF_DIR/building.yaml" ]]; then
    note "the example config's lidar pipeline needs your building's map as $CONF_DIR/building.yaml"
    note "(companion map build LOG --format carmen|ros --out $CONF_DIR/building.yaml); until then"
    note "the service stops at once with exit 2 and the missing file named in the journal"
fi

note "systemd unit $UNIT_DIR/$UNIT_NAME"
run install -m 0644 "$SRC_DIR/systemd/$UNIT_NAME" "$UNIT_DIR/$UNIT_NAME"
run systemd-analyze verify "$UNIT_DIR/$UNIT_NAME"
run systemctl daemon-reload
if systemctl is-active --quiet "$UNIT_NAME" 2>/dev/null; then
    # Already running (an upgrade): restart so the new code is used.
    run systemctl enable "$UNIT_NAME"
    run systemctl restart "$UNIT_NAME"
else
    run systemctl enable --now "$UNIT_NAME"
fi

note "done. Logs: journalctl -u ${UNIT_NAME%.service} -f"
note "after editing $CONF_FILE: systemctl restart ${UNIT_NAME%.service}"
