// The Khronos glTF validator on GLB files: one JSON line per file with its issue counts and messages.
// Usage: node tests/js/validate.mjs FILE.glb ...   (exit 0; the caller judges the counts)
import { readFile } from "node:fs/promises";
import validator from "gltf-validator";

for (const path of process.argv.slice(2)) {
  const report = await validator.validateBytes(new Uint8Array(await readFile(path)), { maxIssues: 50 });
  const { numErrors, numWarnings, numInfos, numHints, messages } = report.issues;
  console.log(JSON.stringify({ path, numErrors, numWarnings, numInfos, numHints,
                               messages: messages.map((m) => `${m.code} ${m.pointer ?? ""}: ${m.message}`) }));
}
