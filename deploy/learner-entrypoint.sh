#!/bin/sh
# Entry point of the learner image: runs `learner` (or `eval`, `plot`, `render` when named
# first) as an unprivileged user who can write /runs.
#
# Why it starts as root: compose bind-mounts ./runs, and Docker creates a missing bind-mount
# directory owned by root, which an unprivileged image user cannot write (the learner then
# crash-looped). Like the official database images, it fixes the ownership and drops to an
# unprivileged user before running anything. That user is the owner of the mounted configs
# directory (the person who cloned the repository, so the runs on the host are theirs), or
# the image's own `crawler` (uid 10001) when that owner is root or nothing is mounted.
set -eu
case "${1:-}" in
    learner | eval | plot | render)
        program="$1"
        shift
        ;;
    *) program=learner ;;
esac
binary="/usr/local/bin/$program"
if [ "$(id -u)" != 0 ]; then
    exec "$binary" "$@"
fi
uid=$(stat -c %u /configs)
gid=$(stat -c %g /configs)
if [ "$uid" = 0 ]; then
    uid=10001
    gid=10001
fi
if [ "$(stat -c %u /runs)" = 0 ]; then
    chown "$uid:$gid" /runs
fi
exec setpriv --reuid="$uid" --regid="$gid" --clear-groups --inh-caps=-all --bounding-set=-all "$binary" "$@"
