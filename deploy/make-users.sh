#!/bin/sh
# Make the router's credential file with fresh random passwords, and one file per user holding its
# password (for the services' and tablets' configs). Nothing here belongs in git.
#   deploy/make-users.sh /etc/scrapcell operator viewer cell-real-1 cell-real-2
# (a cell logs in as "cell-<cell_id>"; deploy/zenoh/router.json5 lets each one serve only cell/<cell_id>/**)
set -eu
dir=${1:?usage: make-users.sh DIR USER...}
shift
umask 077
mkdir -p "$dir"
: > "$dir/zenoh-users.txt"
for user in "$@"; do
  pw=$(LC_ALL=C tr -dc 'A-Za-z0-9' < /dev/urandom | head -c 24)  # 24 characters, ~143 bits
  printf '%s:%s\n' "$user" "$pw" >> "$dir/zenoh-users.txt"
  printf '%s\n' "$pw" > "$dir/$user.password"
done
echo "wrote $dir/zenoh-users.txt and one .password file per user"
