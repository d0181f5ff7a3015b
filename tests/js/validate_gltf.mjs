// Validates glTF binaries with the Khronos glTF validator (npm gltf-validator).
// Usage: node tests/js/validate_gltf.mjs FILE.glb [...]; prints one JSON line per file:
// {"file", "errors", "warnings", "infos", "messages": [first errors and warnings]}.
// Exits 1 when any file has an error.
import { readFile } from 'node:fs/promises';
import validator from 'gltf-validator';

let failed = false;
for (const file of process.argv.slice(2)) {
  const bytes = new Uint8Array(await readFile(file));
  const report = await validator.validateBytes(bytes, { maxIssues: 200 });
  const issues = report.issues;
  const messages = issues.messages
    .filter((m) => m.severity <= 1)
    .slice(0, 20)
    .map((m) => `${m.severity === 0 ? 'error' : 'warning'} ${m.code} ${m.pointer || ''}: ${m.message}`);
  if (issues.numErrors > 0) failed = true;
  console.log(JSON.stringify({
    file, errors: issues.numErrors, warnings: issues.numWarnings, infos: issues.numInfos, messages,
  }));
}
process.exit(failed ? 1 : 0);
