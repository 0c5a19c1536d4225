#!/usr/bin/env bash
# HTTPS for the STOW-RS endpoint and the status page by a TLS-terminating
# proxy (docs/dicomweb.md, "HTTPS"; issue 27): a real interslice-server with
# its HTTP listener on loopback, stunnel in front of it running
# docs/examples/stunnel-https.conf as it is (only accept, connect, cert and key
# replaced), curl as the client:
#  (a) with the CA (--cacert): GET /status.json with the admin token -> 200,
#      POST a STOW-RS body of two instances with a valid token -> 200 and a
#      ReferencedSOPSequence of both;
#  (b) a client that does not trust the CA (the system store, another CA)
#      fails the handshake (curl exit 60), and the proxy keeps serving;
#  (c) plain HTTP to the TLS port gets no HTTP answer.
#   bash tests/server/net/dicomweb/https_proxy_test.sh SERVER_BINARY
# Needs stunnel, curl, openssl and python3 (tests/CMakeLists: require-tool.sh
# skips it outside CI when one is missing).
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(cd "$here/../../../.." && pwd)"
server_binary="${1:?usage: https_proxy_test.sh SERVER_BINARY}"
example="$repo/docs/examples/stunnel-https.conf"
series="$repo/tests/data/ct-thick"
[ -x "$server_binary" ] || { echo "FAIL: $server_binary is not executable"; exit 1; }

tmp="$(mktemp -d "${TMPDIR:-/tmp}/https-proxy.XXXXXX")"
server_pid=""
stunnel_pid=""
cleanup() {
  # Only the processes this script started, by their ids.
  [ -n "$stunnel_pid" ] && kill "$stunnel_pid" 2>/dev/null || true
  [ -n "$server_pid" ] && kill "$server_pid" 2>/dev/null || true
  wait 2>/dev/null || true
  rm -rf "$tmp"
}
trap cleanup EXIT

failures=0
fail() {
  echo "FAIL: $*"
  failures=$((failures + 1))
}
show_logs() {
  echo "--- server log (tail)"; tail -n 30 "$tmp/server.log" 2>/dev/null || true
  echo "--- stunnel log (tail)"; tail -n 30 "$tmp/stunnel.log" 2>/dev/null || true
}
die() {
  echo "FAIL: $*"
  show_logs
  exit 1
}

# A test CA, a server certificate it signs for 127.0.0.1 and localhost, and
# another CA that signed nothing here.
(
  cd "$tmp"
  openssl req -x509 -newkey rsa:2048 -nodes -days 2 -subj /CN=test-ca \
    -keyout ca.key -out ca.pem
  openssl req -newkey rsa:2048 -nodes -subj /CN=localhost \
    -keyout server.key -out server.csr
  printf 'subjectAltName=IP:127.0.0.1,DNS:localhost\n' >san.ext
  openssl x509 -req -in server.csr -CA ca.pem -CAkey ca.key -CAcreateserial \
    -days 2 -extfile san.ext -out server.pem
  openssl req -x509 -newkey rsa:2048 -nodes -days 2 -subj /CN=other-ca \
    -keyout other-ca.key -out other-ca.pem
) >"$tmp/openssl.log" 2>&1 || { cat "$tmp/openssl.log"; die "openssl could not make the test certificates"; }

# The server: tokens (alice submits, ops is the admin), no rules (the
# instances are kept in the series assembly; nothing is interpolated), the
# DICOM listener (STOW-RS needs it) and the HTTP listener on loopback, on
# ports the kernel picks (read back from the port file).
printf 'alice:tok-alice\nops:tok-ops\n' >"$tmp/tokens"
printf 'stable_seconds: 600\nrules: []\n' >"$tmp/rules.yaml"
"$server_binary" --spool "$tmp/spool" --listen 127.0.0.1:0 \
  --port-file "$tmp/ports" --auth-token-file "$tmp/tokens" \
  --admin-identity ops --dicom-listen 127.0.0.1:0 --rules "$tmp/rules.yaml" \
  --http-listen 127.0.0.1:0 --audit-log "$tmp/audit.jsonl" \
  >"$tmp/server.log" 2>&1 &
server_pid=$!
# The port file: gRPC, metrics, DICOM, HTTP (server/app/server.cc), written once
# every listener is up.
deadline=$((SECONDS + 120))
http_port=""
while [ -z "$http_port" ]; do
  kill -0 "$server_pid" 2>/dev/null || die "the server ended during start-up"
  [ "$SECONDS" -lt "$deadline" ] || die "the server wrote no port file within 120 s"
  if [ -f "$tmp/ports" ] && [ "$(wc -l <"$tmp/ports")" -ge 4 ]; then
    http_port="$(sed -n 4p "$tmp/ports")"
  else
    sleep 0.2
  fi
done
[ "$http_port" -gt 0 ] || die "the port file names no HTTP port"

# stunnel with the documented configuration. Only the four site-specific
# values are replaced, each of which must be in the example exactly once (a
# renamed or removed option fails here rather than testing something else).
tls_port="$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')"
config="$tmp/stunnel.conf"
cp "$example" "$config"
replace() {  # OPTION VALUE
  local count
  count="$(grep -c "^$1 = " "$config" || true)"
  [ "$count" = 1 ] || die "docs/examples/stunnel-https.conf: expected one '$1 = ' line, found $count"
  sed -i "s|^$1 = .*|$1 = $2|" "$config"
}
replace accept "127.0.0.1:$tls_port"
replace connect "127.0.0.1:$http_port"
replace cert "$tmp/server.pem"
replace key "$tmp/server.key"
stunnel "$config" >"$tmp/stunnel.log" 2>&1 &
stunnel_pid=$!

# curl: prints "HTTP_CODE EXIT_CODE" on the last line, the body before it.
curl_https() {
  local rc=0
  curl -sS --max-time 60 -w '\n%{http_code}' "$@" 2>>"$tmp/curl.err" || rc=$?
  echo " $rc"
}
base="https://127.0.0.1:$tls_port"

# Ready when a request through the proxy is answered (it may take a moment
# for stunnel to listen).
deadline=$((SECONDS + 60))
until [ "$(curl_https --cacert "$tmp/ca.pem" -o /dev/null "$base/status.json" | tail -n 1)" = "401 0" ]; do
  kill -0 "$stunnel_pid" 2>/dev/null || die "stunnel ended (its configuration is in $config)"
  [ "$SECONDS" -lt "$deadline" ] || die "no answer through stunnel within 60 s"
  sleep 0.2
done

# (a) The status page with the admin token, over HTTPS.
answer="$(curl_https --cacert "$tmp/ca.pem" -u x:tok-ops "$base/status.json")"
last="$(tail -n 1 <<<"$answer")"
[ "$last" = "200 0" ] || fail "(a) GET /status.json over HTTPS: got '$last', want '200 0'"
if ! head -n -1 <<<"$answer" | python3 -c 'import json, sys; d = json.load(sys.stdin); sys.exit(0 if isinstance(d.get("jobs"), list) else 1)'; then
  fail "(a) /status.json over HTTPS is not the status JSON (no jobs list)"
fi

# (a) A STOW-RS body of two instances with a valid token, over HTTPS: 200,
# both referenced.
mapfile -t instances < <(find "$series" -name '*.dcm' | sort | head -n 2)
[ "${#instances[@]}" = 2 ] || die "expected two instances in $series"
{
  for f in "${instances[@]}"; do
    printf -- '--stow-https-test\r\nContent-Type: application/dicom\r\n\r\n'
    cat "$f"
    printf '\r\n'
  done
  printf -- '--stow-https-test--\r\n'
} >"$tmp/stow.body"
answer="$(curl_https --cacert "$tmp/ca.pem" -u x:tok-alice \
  -H 'Content-Type: multipart/related; type="application/dicom"; boundary=stow-https-test' \
  --data-binary "@$tmp/stow.body" "$base/dicomweb/studies")"
last="$(tail -n 1 <<<"$answer")"
[ "$last" = "200 0" ] || fail "(a) STOW-RS over HTTPS: got '$last', want '200 0': $(head -c 300 <<<"$answer")"
referenced="$(head -n -1 <<<"$answer" | python3 -c '
import json, sys
try:
    print(len(json.load(sys.stdin)["00081199"]["Value"]))
except Exception as e:
    print("unreadable:", type(e).__name__)')"
[ "$referenced" = 2 ] || fail "(a) STOW-RS over HTTPS: ReferencedSOPSequence has '$referenced' items, want 2"
# The same without a token is refused behind the proxy as well.
last="$(curl_https --cacert "$tmp/ca.pem" -o /dev/null \
  -H 'Content-Type: multipart/related; type="application/dicom"; boundary=stow-https-test' \
  --data-binary "@$tmp/stow.body" "$base/dicomweb/studies" | tail -n 1)"
[ "$last" = "401 0" ] || fail "(a) STOW-RS over HTTPS without a token: got '$last', want '401 0'"

# (b) A client that does not trust the CA: curl's "SSL peer certificate or
# SSH remote key was not OK" (60), no HTTP answer.
last="$(curl_https -u x:tok-ops -o /dev/null "$base/status.json" | tail -n 1)"
[ "$last" = "000 60" ] || fail "(b) a client with the system CAs only: got '$last', want '000 60'"
last="$(curl_https --cacert "$tmp/other-ca.pem" -u x:tok-ops -o /dev/null "$base/status.json" | tail -n 1)"
[ "$last" = "000 60" ] || fail "(b) a client trusting another CA: got '$last', want '000 60'"

# (c) Plain HTTP to the TLS port: stunnel refuses the handshake and closes;
# curl gets no HTTP answer (52: empty reply, 56: connection reset).
last="$(curl_https -u x:tok-ops -o /dev/null "http://127.0.0.1:$tls_port/status.json" | tail -n 1)"
case "$last" in
  "000 52" | "000 56") ;;
  *) fail "(c) plain HTTP to the TLS port: got '$last', want no HTTP answer ('000 52' or '000 56')" ;;
esac

# Still serving after the refused clients.
last="$(curl_https --cacert "$tmp/ca.pem" -u x:tok-ops -o /dev/null "$base/status.json" | tail -n 1)"
[ "$last" = "200 0" ] || fail "the proxy stopped serving after the refused clients: got '$last'"

# The server stops cleanly (SIGTERM, exit code 0).
kill -TERM "$server_pid"
rc=0
wait "$server_pid" || rc=$?
server_pid=""
[ "$rc" = 0 ] || fail "the server exited with $rc after SIGTERM"

if [ "$failures" -gt 0 ]; then
  show_logs
  echo "--- curl errors"; cat "$tmp/curl.err" 2>/dev/null || true
  echo "https_proxy_test: $failures check(s) failed"
  exit 1
fi
echo "https_proxy_test: passed (stunnel $tls_port -> interslice HTTP $http_port)"
