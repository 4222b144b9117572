// Validates GLB files with the Khronos glTF validator (npm "gltf-validator", pinned in package.json).
// Usage: node validate_gltf.mjs FILE.glb...; prints one JSON report per file (the issue counts and the
// messages), exits 1 when any file has an error.
import { readFile } from "node:fs/promises";
import { createRequire } from "node:module";

const validator = createRequire(import.meta.url)("gltf-validator");
let failed = false;
for (const path of process.argv.slice(2)) {
  const report = await validator.validateBytes(new Uint8Array(await readFile(path)), { uri: path });
  const { numErrors, numWarnings, numInfos, numHints, messages } = report.issues;
  console.log(JSON.stringify({ path, validatorVersion: report.validatorVersion, numErrors, numWarnings, numInfos, numHints, messages }));
  failed ||= numErrors > 0;
}
process.exit(failed ? 1 : 0);
