#!/usr/bin/env bash
# A development certificate authority for the fleet link, and everything signed by it:
#
#   make-dev-ca.sh OUT_DIR ENDPOINT ROBOT_ID...                        one router on ENDPOINT
#   make-dev-ca.sh --site NAME=ENDPOINT... OUT_DIR ENDPOINT ROBOT_ID...  two tiers: site routers
#                                                                      under a cloud router on ENDPOINT
#
#   OUT_DIR/ca.pem, ca-key.pem            the CA (keep the key off the robots)
#   OUT_DIR/router.{pem,key}              the site router (CN router, SAN localhost + 127.0.0.1)
#   OUT_DIR/<robot-id>.{pem,key}          one per robot (CN = robot id)
#   OUT_DIR/inference.{pem,key}           the inference servers (CN inference)
#   OUT_DIR/dashboard.{pem,key}           fleet dashboards (CN dashboard)
#   OUT_DIR/store.{pem,key}               the fleet's history store (CN store)
#   OUT_DIR/router.json5                  router: TLS listener on ENDPOINT, mutual TLS, access control
#   OUT_DIR/<identity>.json5              client side for each identity: its certificate, the CA
#
# With --site (the fleet's two tiers, from this folder's site-router.json5 and cloud-router.json5):
#   OUT_DIR/cloud-router.{pem,key,json5}  the cloud router on ENDPOINT (CN cloud-router); the
#                                         inference, dashboard and store identities connect here
#   OUT_DIR/site-NAME.{pem,key,json5}     each site router on its own endpoint (CN site-NAME),
#                                         linked up to the cloud router; every robot's rules on each
#                                         site (a robot fails over to another site's router), and
#                                         the robots' client files list every site
#   (no router.json5)
#
# ENDPOINT is a zenoh TLS locator, e.g. tls/127.0.0.1:7448 or tls/site-router.local:7447.
# Access control on the router (default deny; deny rules win over allow rules):
#   robot R      reads and writes nori/R/** only, and may not publish actions nor
#                acknowledgements, even its own
#   inference    reads nori/*/observation and nori/*/layout, publishes nori/*/actions
#   dashboard    reads nori/*/{state,events,layout,alive,status}; publishes nothing
#   store        reads nori/*/{events,state,layout,blackbox/chunk}, publishes nori/*/acks and
#                nori/*/blackbox/ack only
# For production use a real CA and keep each robot's key on its robot only.
set -euo pipefail
sites=()
while [ "${1:-}" = --site ]; do
  [[ ${2:-} =~ ^[A-Za-z0-9_-]{1,32}=.+$ ]] || { echo "--site NAME=ENDPOINT, not '${2:-}'" >&2; exit 2; }
  sites+=("$2")
  shift 2
done
if [ $# -lt 3 ]; then
  echo "usage: $0 [--site NAME=ENDPOINT]... OUT_DIR ENDPOINT ROBOT_ID..." >&2
  exit 2
fi
out=$(mkdir -p "$1" && cd "$1" && pwd)
endpoint=$2
shift 2
robots=("$@")
for r in "${robots[@]}"; do
  [[ $r =~ ^[A-Za-z0-9_-]{1,64}$ ]] || { echo "robot id '$r': use 1-64 of A-Z a-z 0-9 - _" >&2; exit 2; }
done
command -v openssl >/dev/null || { echo "openssl is needed (apt-get install openssl)" >&2; exit 1; }

days=825
openssl req -x509 -newkey rsa:2048 -nodes -days "$days" -subj "/CN=nori dev CA" \
  -keyout "$out/ca-key.pem" -out "$out/ca.pem" 2>/dev/null

# sign NAME CN [SAN]: a key and a certificate signed by the CA.
sign() {
  local name=$1 cn=$2 san=${3:-}
  openssl req -newkey rsa:2048 -nodes -subj "/CN=$cn" \
    -keyout "$out/$name.key" -out "$out/$name.csr" 2>/dev/null
  local ext="$out/$name.ext"
  {
    echo "basicConstraints=CA:FALSE"
    echo "keyUsage=digitalSignature,keyEncipherment"
    echo "extendedKeyUsage=serverAuth,clientAuth"
    if [ -n "$san" ]; then echo "subjectAltName=$san"; fi
  } >"$ext"
  openssl x509 -req -in "$out/$name.csr" -CA "$out/ca.pem" -CAkey "$out/ca-key.pem" \
    -CAcreateserial -days "$days" -extfile "$ext" -out "$out/$name.pem" 2>/dev/null
  rm -f "$out/$name.csr" "$ext"
}

for id in "${robots[@]}" inference dashboard store; do
  sign "$id" "$id" "DNS:$id"
done

# The endpoints robots connect to: the router's, or every site's.
robot_endpoints="\"$endpoint\""
if [ ${#sites[@]} -gt 0 ]; then
  robot_endpoints=$(for s in "${sites[@]}"; do printf '"%s", ' "${s#*=}"; done)
  robot_endpoints=${robot_endpoints%, }
fi

# Client side of one identity.
for id in "${robots[@]}" inference dashboard store; do
  connect="\"$endpoint\""
  for r in "${robots[@]}"; do [ "$r" != "$id" ] || connect=$robot_endpoints; done
  cat >"$out/$id.json5" <<JSON
// zenoh client configuration of identity "$id" (made by make-dev-ca.sh).
{
  mode: "client",
  connect: { endpoints: [$connect] },
  scouting: { multicast: { enabled: false } },
  transport: {
    // A router that accepts the connection but does not answer (frozen) is given up after 2 s,
    // and the next endpoint tried (docs/fleet-sizing.md, "Leases").
    unicast: { open_timeout: 2000 },
    link: {
      tx: { lease: 5000, keep_alive: 4 },
      tls: {
        root_ca_certificate: "$out/ca.pem",
        connect_certificate: "$out/$id.pem",
        connect_private_key: "$out/$id.key",
        enable_mtls: true,
      },
    },
  },
}
JSON
done

chmod 600 "$out"/*.key "$out/ca-key.pem"

if [ ${#sites[@]} -gt 0 ]; then
  # The two tiers from the shipped templates. Each substitution must take: a template that no
  # longer has the line it replaces fails here, not in a router that silently allows the example.
  here=$(cd "$(dirname "$0")" && pwd)
  # expand TEMPLATE OUT SED_SCRIPT: the template without its comments through sed, each line
  # naming the example robot once per robot; fails if a placeholder survives.
  expand() {
    local template=$1 target=$2 script=$3
    {
      echo "// made by make-dev-ca.sh from $template"
      sed -e '/^[[:space:]]*\/\//d' -e "$script" "$here/$template" | while IFS= read -r line; do
        if [[ $line == *robot-0001* ]]; then
          for r in "${robots[@]}"; do echo "${line//robot-0001/$r}"; done
        else
          echo "$line"
        fi
      done
    } >"$target"
    if grep -qE '/etc/nori|example\.org|0\.0\.0\.0|\[::\]|robot-0001|site-home-0001' "$target"; then
      echo "$template: a placeholder was not replaced in $target" >&2
      exit 1
    fi
  }
  sign cloud-router cloud-router "DNS:localhost,IP:127.0.0.1"
  site_names=$(for s in "${sites[@]}"; do printf '"site-%s", ' "${s%%=*}"; done)
  expand cloud-router.json5 "$out/cloud-router.json5" "
    s|\"tls/\[::\]:7447\"|\"$endpoint\"|
    s|/etc/nori/tls/|$out/|g
    s|\"site-home-0001\", \"site-lab\"|${site_names%, }|"
  for s in "${sites[@]}"; do
    name=${s%%=*} site_endpoint=${s#*=}
    sign "site-$name" "site-$name" "DNS:localhost,IP:127.0.0.1"
    expand site-router.json5 "$out/site-$name.json5" "
      s|\"tls/0.0.0.0:7447\"|\"$site_endpoint\"|
      s|\"tls/fleet.example.org:7447\"|\"$endpoint\"|
      s|/etc/nori/tls/site\.|$out/site-$name.|g
      s|/etc/nori/tls/|$out/|g"
  done
  chmod 600 "$out"/*.key
  echo "made a development CA, a cloud router, ${#sites[@]} site router(s), ${#robots[@]} robot(s), inference, dashboard and store identities in $out"
  exit 0
fi

sign router router "DNS:localhost,IP:127.0.0.1"
# Router: TLS only, client certificates required, access control by certificate name.
all='"put", "delete", "declare_subscriber", "query", "declare_queryable", "reply", "liveliness_token", "declare_liveliness_subscriber", "liveliness_query"'
{
  cat <<JSON
// zenoh router of the fleet (made by make-dev-ca.sh): mutual TLS on $endpoint, access control.
{
  mode: "router",
  listen: { endpoints: ["$endpoint"] },
  scouting: { multicast: { enabled: false } },
  transport: {
    unicast: { max_sessions: 10000 },
    link: {
      tx: { lease: 5000, keep_alive: 4 },
      tls: {
        root_ca_certificate: "$out/ca.pem",
        listen_certificate: "$out/router.pem",
        listen_private_key: "$out/router.key",
        enable_mtls: true,
      },
    },
  },
  access_control: {
    enabled: true,
    default_permission: "deny",
    rules: [
JSON
  for r in "${robots[@]}"; do
    cat <<JSON
      { id: "own-$r", permission: "allow", flows: ["ingress", "egress"], messages: [$all], key_exprs: ["nori/$r/**"] },
JSON
  done
  cat <<JSON
      { id: "robots-see-interest", permission: "allow", flows: ["egress"], messages: ["declare_subscriber", "declare_liveliness_subscriber"], key_exprs: ["nori/**"] },
      { id: "robots-publish-no-commands", permission: "deny", flows: ["ingress"], messages: ["put", "delete"], key_exprs: ["nori/*/actions", "nori/*/acks", "nori/*/blackbox/ack"] },
      { id: "inference-observes", permission: "allow", flows: ["ingress"], messages: ["declare_subscriber"], key_exprs: ["nori/*/observation", "nori/*/layout"] },
      { id: "inference-hears", permission: "allow", flows: ["egress"], messages: ["put"], key_exprs: ["nori/*/observation", "nori/*/layout"] },
      { id: "inference-acts", permission: "allow", flows: ["ingress"], messages: ["put"], key_exprs: ["nori/*/actions"] },
      { id: "inference-acts-interest", permission: "allow", flows: ["egress"], messages: ["declare_subscriber"], key_exprs: ["nori/*/actions"] },
      { id: "dashboard-asks", permission: "allow", flows: ["ingress"], messages: ["declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"], key_exprs: ["nori/*/state", "nori/*/events", "nori/*/layout", "nori/*/alive", "nori/*/status", "nori/*/preview", "nori/*/scan"] },
      { id: "dashboard-hears", permission: "allow", flows: ["egress"], messages: ["put", "reply", "liveliness_token", "declare_queryable"], key_exprs: ["nori/*/state", "nori/*/events", "nori/*/layout", "nori/*/alive", "nori/*/status", "nori/*/preview", "nori/*/scan"] },
      { id: "store-asks", permission: "allow", flows: ["ingress"], messages: ["declare_subscriber"], key_exprs: ["nori/*/events", "nori/*/state", "nori/*/layout", "nori/*/blackbox/chunk"] },
      { id: "store-hears", permission: "allow", flows: ["egress"], messages: ["put"], key_exprs: ["nori/*/events", "nori/*/state", "nori/*/layout", "nori/*/blackbox/chunk"] },
      { id: "store-acknowledges", permission: "allow", flows: ["ingress"], messages: ["put"], key_exprs: ["nori/*/acks", "nori/*/blackbox/ack"] },
      { id: "store-acknowledges-interest", permission: "allow", flows: ["egress"], messages: ["declare_subscriber"], key_exprs: ["nori/*/acks", "nori/*/blackbox/ack"] },
      { id: "read-only", permission: "deny", flows: ["ingress"], messages: ["put", "delete", "declare_queryable", "liveliness_token"], key_exprs: ["nori/**"] },
    ],
    subjects: [
JSON
  for r in "${robots[@]}"; do
    echo "      { id: \"$r\", cert_common_names: [\"$r\"] },"
  done
  cat <<JSON
      { id: "inference", cert_common_names: ["inference"] },
      { id: "dashboard", cert_common_names: ["dashboard"] },
      { id: "store", cert_common_names: ["store"] },
    ],
    policies: [
JSON
  for r in "${robots[@]}"; do
    echo "      { rules: [\"own-$r\", \"robots-see-interest\", \"robots-publish-no-commands\"], subjects: [\"$r\"] },"
  done
  cat <<JSON
      { rules: ["inference-observes", "inference-hears", "inference-acts", "inference-acts-interest"], subjects: ["inference"] },
      { rules: ["dashboard-asks", "dashboard-hears", "read-only"], subjects: ["dashboard"] },
      { rules: ["store-asks", "store-hears", "store-acknowledges", "store-acknowledges-interest"], subjects: ["store"] },
    ],
  },
}
JSON
} >"$out/router.json5"
chmod 600 "$out"/*.key "$out/ca-key.pem"
echo "made a development CA, router, ${#robots[@]} robot(s), inference, dashboard and store identities in $out"
