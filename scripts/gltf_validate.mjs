// Validate .glb/.gltf files with the Khronos glTF-Validator; prints one JSON report per file
// ({file, errors, warnings, infos, hints, messages}) and exits 1 if any file has errors or warnings.
// Usage: node scripts/gltf_validate.mjs a.glb [b.glb ...]
import { readFileSync } from "node:fs";
import { createRequire } from "node:module";
import { dirname, resolve } from "node:path";
const require = createRequire(import.meta.url);
const validator = require("gltf-validator");

let bad = 0;
for (const file of process.argv.slice(2)) {
  const bytes = new Uint8Array(readFileSync(file));
  const report = await validator.validateBytes(bytes, {
    uri: file,
    maxIssues: 100,
    externalResourceFunction: (uri) =>
      Promise.resolve(new Uint8Array(readFileSync(resolve(dirname(file), decodeURIComponent(uri))))),
  });
  const i = report.issues;
  const out = { file, errors: i.numErrors, warnings: i.numWarnings, infos: i.numInfos, hints: i.numHints, messages: i.messages };
  console.log(JSON.stringify(out));
  if (i.numErrors > 0 || i.numWarnings > 0) bad++;
}
process.exit(bad ? 1 : 0);
