#!/bin/sh
# The compose file's nginx (compose.yaml): fill deploy/nginx.conf the way deploy/local-cluster does, from the
# environment (DIMGESTOR_NGINX_DIR, DIMGESTOR_LISTEN, DIMGESTOR_UPSTREAM), then run nginx in the foreground.
# Only those three are replaced: nginx's own $variables stay. Extra arguments go to nginx (e.g. -t to check).
set -eu
: "${DIMGESTOR_NGINX_DIR:?}" "${DIMGESTOR_LISTEN:?}" "${DIMGESTOR_UPSTREAM:?}"
mkdir -p "$DIMGESTOR_NGINX_DIR"
envsubst '${DIMGESTOR_NGINX_DIR} ${DIMGESTOR_LISTEN} ${DIMGESTOR_UPSTREAM}' \
    < "$(dirname "$0")/nginx.conf" > "$DIMGESTOR_NGINX_DIR/nginx.conf"
exec nginx -p "$DIMGESTOR_NGINX_DIR" -c "$DIMGESTOR_NGINX_DIR/nginx.conf" -g 'daemon off;' "$@"
