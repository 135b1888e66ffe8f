#!/usr/bin/env bash
# The whole matopt loop from a shell, with grpcurl (or `buf curl`) and server reflection: no
# stubs, no .proto on the client's side. Uploads the example scene bundle, loads it, lists its
# parameters, renders a reference with an override, handles two errors, optimizes the plate's
# colour back from grey, watches the job to its end, and fetches its result and its history
# page by page. Prints the recovered value as JSON on stdout; the steps go to stderr.
#
#   walkthrough.sh HOST:PORT [TOKEN] [CA_PEM]
#
# grpcurl is used when it is on PATH; otherwise `buf curl`: $BUF, else buf on PATH, else buf
# fetched once by Node.js's npx into npm's cache, at the version the Node.js example's lock
# file pins. With CA_PEM the connection uses TLS and trusts that certificate authority. JSON
# is taken apart with python3.
set -euo pipefail

SERVER=${1:?usage: walkthrough.sh HOST:PORT [TOKEN] [CA_PEM]}
TOKEN=${2:-}
CA=${3:-}
HERE=$(cd "$(dirname "$0")" && pwd)
SCENE=$(cd "$HERE/../scene" && pwd)
KEY=plate.bsdf.reflectance.value   # the plate's colour in scene/plate.xml
TRUTH='[0.7, 0.3, 0.2]'
ITERATIONS=${ITERATIONS:-40}

say() { echo "$@" >&2; }

# buf_from_npm: the path of buf as npx fetches it (once; later runs find it in npm's cache).
buf_from_npm() {
    local version
    version=$(python3 -c 'import json, sys
print(json.load(open(sys.argv[1]))["packages"]["node_modules/@bufbuild/buf"]["version"])' \
              "$HERE/../node/package-lock.json")
    say "fetching buf $version with npx (neither grpcurl nor buf is on PATH)"
    npx --yes --package "@bufbuild/buf@$version" -c 'command -v buf'
}

if ! command -v grpcurl >/dev/null && [ -z "${BUF:-}" ]; then
    if command -v buf >/dev/null; then
        BUF=buf
    elif command -v npx >/dev/null; then
        BUF=$(buf_from_npm)
    else
        say "walkthrough.sh: needs grpcurl, or buf, or Node.js (whose npx fetches buf) on PATH"
        exit 2
    fi
fi

# call SERVICE/METHOD: the request (JSON; several documents for a client stream) on stdin,
# the response(s) as JSON on stdout. Fails with the status and message on stderr.
call() {
    local headers=()
    [ -n "$TOKEN" ] && headers=(-H "authorization: Bearer $TOKEN")
    if command -v grpcurl >/dev/null; then
        local tls=(-plaintext)
        [ -n "$CA" ] && tls=(-cacert "$CA")
        grpcurl "${tls[@]}" "${headers[@]}" -d @ "$SERVER" "matopt.v1.$1"
    else
        local url="http://$SERVER" tls=(--http2-prior-knowledge)
        [ -n "$CA" ] && url="https://$SERVER" tls=(--cacert "$CA")
        "$BUF" curl --protocol grpc "${tls[@]}" "${headers[@]}" -d @- "$url/matopt.v1.$1"
    fi
}

# get EXPRESSION: evaluates a Python expression over the JSON document `d` read from stdin.
get() { python3 -c 'import json, sys; d = json.load(sys.stdin); print(eval(sys.argv[1]))' "$1"; }

# expect_error CODE WHAT SERVICE/METHOD: the call must fail with CODE (e.g. NotFound); the
# request is on stdin. grpcurl writes codes as NotFound, buf curl as not_found.
expect_error() {
    local out
    if out=$(call "$3" 2>&1); then
        say "$2: expected $1, got: $out"; exit 1
    fi
    local flat=${1//_/}
    if ! tr -d '_' <<<"$out" | grep -qi "$flat"; then
        say "$2: expected $1, got: $out"; exit 1
    fi
    say "  $2: $(tr '\n' ' ' <<<"$out" | head -c 200)"
}

info=$(echo '{}' | call ServerService/GetServerInfo)
say "matoptd $(get 'd["version"]' <<<"$info") ($(get 'd["variant"]' <<<"$info")) as $(get 'd["user"]' <<<"$info")"

# 1. Upload what the daemon lacks: FindMissingBlobs, then UploadBlob for each missing file.
cd "$SCENE"
mapfile -t paths < <(find . -type f | sed 's|^\./||' | sort)
declare -A digest
for p in "${paths[@]}"; do digest[$p]=$(sha256sum "$p" | cut -d' ' -f1); done
wanted=$(printf '"%s",' "${digest[@]}")
missing=$(echo "{\"sha256\": [${wanted%,}]}" | call BlobService/FindMissingBlobs |
          get '" ".join(d.get("missingSha256", []))')
for p in "${paths[@]}"; do
    [[ " $missing " == *" ${digest[$p]} "* ]] || continue
    # The header, then the content in chunks of at most 1 MiB (base64 in JSON).
    { echo "{\"header\": {\"sha256\": \"${digest[$p]}\", \"sizeBytes\": \"$(stat -c %s "$p")\"}}"
      split -b 1M --filter='echo "{\"chunk\": \"$(base64 -w0)\"}"' "$p"
    } | call BlobService/UploadBlob >/dev/null
done
say "uploaded $(wc -w <<<"$missing") of ${#paths[@]} bundle files"
files=$(for p in "${paths[@]}"; do printf '{"path": "%s", "sha256": "%s"},' "$p" "${digest[$p]}"; done)

# 2. Load the scene and list what can be optimized.
scene=$(echo "{\"mainFile\": \"plate.xml\", \"files\": [${files%,}], \"overrides\": {\"res\": \"32\"}}" |
        call SceneService/CreateScene | get 'd["name"]')
keys=$(echo "{\"name\": \"$scene\"}" | call SceneService/ListSceneParameters |
       get '" ".join(p["key"] for p in d["parameters"])')
say "$scene: $keys"
[[ " $keys " == *" $KEY "* ]] || { say "$KEY is not a parameter"; exit 1; }

# 3. A synthetic reference: the scene rendered with the true colour.
reference=$(echo "{\"name\": \"$scene\", \"spp\": 64, \"parameters\": [{\"key\": \"$KEY\", \"value\": $TRUTH}]}" |
            call SceneService/RenderScene | get 'd["images"][0]["exrBlob"]')

# 4. Two errors, handled: a job on a key the scene lacks, and a job that does not exist.
echo "{\"spec\": {\"scene\": \"$scene\", \"references\": [{\"blob\": \"$reference\"}], \"parameters\": [{\"key\": \"no.such.key\"}]}}" |
    expect_error InvalidArgument "a job on an unknown key" JobService/CreateJob
echo '{"name": "jobs/000000000000"}' | expect_error NotFound "a job that does not exist" JobService/GetJob

# 5. Optimize from grey, and watch until the stream ends with the final state.
job=$(echo "{\"spec\": {\"scene\": \"$scene\", \"references\": [{\"blob\": \"$reference\", \"filename\": \"reference.exr\"}],
              \"parameters\": [{\"key\": \"$KEY\", \"initialValue\": [0.5, 0.5, 0.5]}],
              \"iterations\": $ITERATIONS, \"spp\": 8, \"groundTruth\": [{\"key\": \"$KEY\", \"value\": $TRUTH}]}}" |
      call JobService/CreateJob | get 'd["name"]')
say "$job queued; watching"
echo "{\"name\": \"$job\"}" | call JobService/WatchJob >/dev/null
final=$(echo "{\"name\": \"$job\"}" | call JobService/GetJob)
state=$(get 'd["state"]' <<<"$final")
say "$job $state after $(get 'd.get("iteration", 0)' <<<"$final") iterations"
[ "$state" = JOB_STATE_SUCCEEDED ] || { say "the job ended $state"; exit 1; }

# 6. The result, and the whole history page by page.
value=$(echo "{\"name\": \"$job\", \"which\": \"WHICH_BEST\"}" | call JobService/GetJobResult |
        get "next(p['value'] for p in d['parameters'] if p['key'] == '$KEY')")
records=0 token=""
while :; do
    page=$(echo "{\"name\": \"$job\", \"pageSize\": 16, \"pageToken\": \"$token\"}" | call JobService/GetJobHistory)
    records=$((records + $(get 'len(d.get("iterations", []))' <<<"$page")))
    token=$(get 'd.get("nextPageToken", "")' <<<"$page")
    [ -n "$token" ] || break
done
say "$records iterations recorded"
echo "{\"job\": \"$job\", \"key\": \"$KEY\", \"value\": $value, \"truth\": $TRUTH, \"iterations\": $records}"
