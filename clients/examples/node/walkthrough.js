#!/usr/bin/env node
// The whole matopt loop from Node.js, with nothing but the .proto file and @grpc/grpc-js:
// upload a scene bundle, load it, list its parameters, render a reference with an override,
// optimize the plate's colour back from a grey start, watch the job, fetch its result and
// history, and handle two errors. Prints the recovered value as JSON on stdout.
//
//   node walkthrough.js --server localhost:50051 [--token TOKEN] [--ca ca.pem]
//                       [--scene ../scene] [--iterations 40]
"use strict";

const crypto = require("node:crypto");
const fs = require("node:fs");
const path = require("node:path");
const { parseArgs } = require("node:util");
const grpc = require("@grpc/grpc-js");
const protoLoader = require("@grpc/proto-loader");

const { values: args } = parseArgs({
  options: {
    server: { type: "string", default: "localhost:50051" },
    token: { type: "string" },
    ca: { type: "string" },
    scene: { type: "string", default: path.join(__dirname, "..", "scene") },
    iterations: { type: "string", default: "40" },
    proto: { type: "string", default: path.join(__dirname, "..", "..", "..", "proto") },
  },
});

const KEY = "plate.bsdf.reflectance.value"; // the plate's colour in scene/plate.xml
const TRUTH = [0.7, 0.3, 0.2];
const CHUNK = 1 << 20; // UploadBlob takes chunks of at most 1 MiB

const log = (...parts) => console.error(...parts);

// gRPC's own retries, as the Python client library has them: a call refused for a moment
// (RESOURCE_EXHAUSTED: too many of one's requests in progress, the daemon names the delay in
// grpc-retry-pushback-ms and google.rpc.RetryInfo; UNAVAILABLE: a restart) goes again, at most
// 5 attempts. A limit that retrying does not lift comes with a pushback of -1: not retried.
// ServerService is left out: it meets no limit, and a wrong address should fail at once.
const SERVICE_CONFIG = {
  methodConfig: [{
    name: ["BlobService", "SceneService", "JobService"].map(
      (s) => ({ service: `matopt.v1.${s}` })),
    retryPolicy: {
      maxAttempts: 5,
      initialBackoff: "0.2s",
      maxBackoff: "5s",
      backoffMultiplier: 2,
      retryableStatusCodes: ["RESOURCE_EXHAUSTED", "UNAVAILABLE"],
    },
  }],
};
const CHANNEL_OPTIONS = {
  "grpc.enable_retries": 1,
  "grpc.service_config": JSON.stringify(SERVICE_CONFIG),
};

function connect() {
  const definition = protoLoader.loadSync("matopt/v1/matopt.proto", {
    includeDirs: [args.proto],
    keepCase: true, // field names as in the .proto: missing_sha256, not missingSha256
    enums: String, // "JOB_STATE_SUCCEEDED" rather than 4
    longs: Number,
    defaults: true,
    oneofs: true,
  });
  const v1 = grpc.loadPackageDefinition(definition).matopt.v1;
  const creds = args.ca
    ? grpc.credentials.createSsl(fs.readFileSync(args.ca))
    : grpc.credentials.createInsecure();
  // Sent with every call: the daemon's --tokens file maps the token to a user.
  const metadata = new grpc.Metadata();
  if (args.token) metadata.set("authorization", `Bearer ${args.token}`);
  const make = (Service) => new Service(args.server, creds, CHANNEL_OPTIONS);
  return {
    blobs: make(v1.BlobService),
    scenes: make(v1.SceneService),
    jobs: make(v1.JobService),
    server: make(v1.ServerService),
    metadata,
  };
}

// Unary calls as promises.
function call(stub, method, request, metadata) {
  return new Promise((resolve, reject) =>
    stub[method](request, metadata, (err, response) => (err ? reject(err) : resolve(response))));
}

const sha256 = (bytes) => crypto.createHash("sha256").update(bytes).digest("hex");

function upload(api, bytes) {
  return new Promise((resolve, reject) => {
    const stream = api.blobs.UploadBlob(api.metadata, (err, blob) => (err ? reject(err) : resolve(blob)));
    stream.write({ header: { sha256: sha256(bytes), size_bytes: bytes.length } });
    for (let at = 0; at < bytes.length; at += CHUNK) stream.write({ chunk: bytes.subarray(at, at + CHUNK) });
    stream.end();
  });
}

// Every file under the bundle folder, as BundleFile paths relative to it.
function bundleFiles(root) {
  const out = [];
  const walk = (dir) => {
    for (const entry of fs.readdirSync(dir, { withFileTypes: true })) {
      const full = path.join(dir, entry.name);
      if (entry.isDirectory()) walk(full);
      else out.push({ path: path.relative(root, full).split(path.sep).join("/"), bytes: fs.readFileSync(full) });
    }
  };
  walk(root);
  return out;
}

// Expects `promise` to fail with `code`; says what the daemon answered.
async function expectError(what, promise, code) {
  try {
    await promise;
  } catch (err) {
    if (err.code !== code) throw err;
    log(`  ${what}: ${grpc.status[err.code]}: ${err.details}`);
    return;
  }
  throw new Error(`${what}: expected ${grpc.status[code]}`);
}

async function main() {
  const api = connect();
  const info = await call(api.server, "GetServerInfo", {}, api.metadata);
  log(`matoptd ${info.version} (${info.variant}) as ${info.user}; losses: ${info.losses.join(", ")}`);

  // 1. Upload what the daemon lacks: FindMissingBlobs, then UploadBlob for each missing one.
  const files = bundleFiles(args.scene).map((f) => ({ ...f, sha256: sha256(f.bytes) }));
  const { missing_sha256: missing } = await call(api.blobs, "FindMissingBlobs",
    { sha256: files.map((f) => f.sha256) }, api.metadata);
  for (const f of files.filter((f) => missing.includes(f.sha256))) await upload(api, f.bytes);
  log(`uploaded ${missing.length} of ${files.length} bundle files`);

  // 2. Load the scene and list what can be optimized.
  const scene = await call(api.scenes, "CreateScene", {
    main_file: "plate.xml",
    files: files.map((f) => ({ path: f.path, sha256: f.sha256 })),
    overrides: { res: "32" },
  }, api.metadata);
  const { parameters } = await call(api.scenes, "ListSceneParameters", { name: scene.name }, api.metadata);
  log(`${scene.name}: ${parameters.map((p) => `${p.key} (${p.kind})`).join(", ")}`);
  if (!parameters.some((p) => p.key === KEY)) throw new Error(`${KEY} is not a parameter`);

  // 3. A synthetic reference: the scene rendered with the true colour.
  const render = await call(api.scenes, "RenderScene",
    { name: scene.name, parameters: [{ key: KEY, value: TRUTH }], spp: 64 }, api.metadata);
  const reference = render.images[0].exr_blob;

  // 4. Two errors, handled: a job on a key the scene lacks, and a job that does not exist.
  await expectError("a job on an unknown key", call(api.jobs, "CreateJob", {
    spec: { scene: scene.name, references: [{ blob: reference }], parameters: [{ key: "no.such.key" }] },
  }, api.metadata), grpc.status.INVALID_ARGUMENT);
  await expectError("a job that does not exist",
    call(api.jobs, "GetJob", { name: "jobs/000000000000" }, api.metadata), grpc.status.NOT_FOUND);

  // 5. Optimize from grey and watch it to the end.
  const job = await call(api.jobs, "CreateJob", {
    spec: {
      scene: scene.name,
      references: [{ blob: reference, filename: "reference.exr" }],
      parameters: [{ key: KEY, initial_value: [0.5, 0.5, 0.5] }],
      iterations: Number(args.iterations),
      spp: 8,
      ground_truth: [{ key: KEY, value: TRUTH }],
    },
  }, api.metadata);
  log(`${job.name} ${job.state}`);
  const final = await new Promise((resolve, reject) => {
    let last = job;
    const watch = api.jobs.WatchJob({ name: job.name }, api.metadata);
    watch.on("data", (event) => {
      if (event.job) last = event.job;
      else if (event.iteration.iteration % 10 === 0) log(`  iteration ${event.iteration.iteration}: loss ${event.iteration.loss.toExponential(3)}`);
    });
    watch.on("end", () => resolve(last));
    watch.on("error", reject);
  });
  log(`${final.name} ${final.state} after ${final.iteration} iterations (${final.stop_reason})`);
  if (final.state !== "JOB_STATE_SUCCEEDED") throw new Error(`job ended ${final.state}: ${final.error}`);

  // 6. The result and the whole history, page by page.
  const result = await call(api.jobs, "GetJobResult", { name: job.name, which: "WHICH_BEST" }, api.metadata);
  const value = result.parameters.find((p) => p.key === KEY).value;
  const history = [];
  let pageToken = "";
  do {
    const page = await call(api.jobs, "GetJobHistory",
      { name: job.name, page_size: 16, page_token: pageToken }, api.metadata);
    history.push(...page.iterations);
    pageToken = page.next_page_token;
  } while (pageToken);
  log(`best iteration ${result.iteration} of ${history.length} recorded`);
  console.log(JSON.stringify({ job: job.name, key: KEY, value, truth: TRUTH, iterations: history.length }));
}

main().catch((err) => {
  log(`error: ${err.details || err.message}`);
  process.exit(1);
});
