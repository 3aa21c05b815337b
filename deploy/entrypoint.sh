#!/bin/sh
# Entry point of both crawler images: runs the image's program (CRAWLER_PROGRAM: `actor` or
# `learner`), or the tool named first (`eval`, `average`, `pick`, `plot`, `render`, in both images), as an
# unprivileged user.
#
# The images run as `crawler` (uid 10001), and then the program starts directly. A compose
# service that bind-mounts host files starts it as root instead (`user: root`, with only the
# capabilities this needs), and it drops to the runtime user, as the official database
# images do. Why:
# - /runs: compose bind-mounts ./runs, and Docker creates a missing bind-mount directory
#   owned by root, which an unprivileged image user cannot write (the learner then
#   crash-looped). The directory is handed to the runtime user first.
# - TLS material: deploy/make-tls.sh writes keys readable by their owner only (0600), and a
#   mounted key belongs to whoever made it on the host, not to the image's user, who then
#   could not read it. Each file given by --tls-ca, --tls-cert or --tls-key (or the
#   CRAWLER_TLS_* variables) is copied into a directory in memory (/dev/shm) that only the
#   runtime user can read, and the program is pointed at the copy. The mounted files stay
#   as they are.
# The runtime user is the owner of the mounted configs directory (the person who cloned the
# repository, so that runs on the host are theirs), or the image's own `crawler` (uid 10001)
# when that owner is root or nothing is mounted.
set -eu
program="${CRAWLER_PROGRAM:?the image sets CRAWLER_PROGRAM}"
case "${1:-}" in
    actor | learner | eval | average | pick | plot | render)
        if [ ! -x "/usr/local/bin/$1" ]; then
            echo "crawler-entrypoint: this image has no $1 (the learner image has learner, eval, average, pick, plot and render; the actor image has actor, eval, average, pick, plot and render)" >&2
            exit 2
        fi
        program="$1"
        shift
        ;;
esac
binary="/usr/local/bin/$program"
if [ "$(id -u)" != 0 ]; then
    exec "$binary" "$@"
fi

uid=$(stat -c %u /configs 2>/dev/null || echo 0)
gid=$(stat -c %g /configs 2>/dev/null || echo 0)
if [ "$uid" = 0 ]; then
    uid=10001
    gid=10001
fi
if [ -d /runs ] && [ "$(stat -c %u /runs)" = 0 ]; then
    chown "$uid:$gid" /runs
fi

# Copies of the TLS files, in memory where /dev/shm is a tmpfs (as in Docker containers).
parent=/dev/shm
[ -d "$parent" ] && [ -w "$parent" ] || parent=/tmp
private=$(mktemp -d "$parent/crawler-tls.XXXXXX")
# private_copy NAME PATH: copies PATH to $private/NAME.pem, readable by the runtime user only,
# and prints the copy's path. A missing file is left as given, so the program's error names it.
private_copy() {
    if [ ! -f "$2" ]; then
        printf '%s' "$2"
        return
    fi
    copy="$private/$1.pem"
    cp "$2" "$copy"
    chmod 0400 "$copy"
    chown "$uid:$gid" "$copy"
    printf '%s' "$copy"
}

# Rewrite the TLS arguments in place: `--tls-key PATH` and `--tls-key=PATH` alike.
pending=""
for argument do
    shift
    if [ -n "$pending" ]; then
        argument=$(private_copy "$pending" "$argument")
        pending=""
    else
        case "$argument" in
            --tls-ca | --tls-cert | --tls-key) pending="${argument#--tls-}" ;;
            --tls-ca=* | --tls-cert=* | --tls-key=*)
                flag="${argument%%=*}"
                argument="$flag=$(private_copy "${flag#--tls-}" "${argument#*=}")"
                ;;
        esac
    fi
    set -- "$@" "$argument"
done
for name in ca cert key; do
    variable="CRAWLER_TLS_$(echo "$name" | tr a-z A-Z)"
    eval "value=\${$variable:-}"
    if [ -n "$value" ]; then
        export "$variable=$(private_copy "$name" "$value")"
    fi
done

# Handed over only now: until the copies are made it stays root's, so that root needs no
# capability to write into a directory it does not own (the compose files grant none).
chown "$uid:$gid" "$private"

# --no-new-privs: nothing the program runs can gain privileges again (setuid files, file
# capabilities).
exec setpriv --reuid="$uid" --regid="$gid" --clear-groups --inh-caps=-all --bounding-set=-all --no-new-privs \
    "$binary" "$@"
