// Validates glTF files with the Khronos glTF-Validator and prints one JSON report per file:
//   node validate_gltf.mjs a.glb b.glb  ->  [{"file", "errors", "warnings", "infos", "messages"}]
import { readFile } from "node:fs/promises";
import validator from "gltf-validator";

const reports = [];
for (const file of process.argv.slice(2)) {
  const data = new Uint8Array(await readFile(file));
  const report = await validator.validateBytes(data, { maxIssues: 1000 });
  reports.push({
    file,
    errors: report.issues.numErrors,
    warnings: report.issues.numWarnings,
    infos: report.issues.numInfos,
    messages: report.issues.messages.map((m) => ({ code: m.code, severity: m.severity, pointer: m.pointer,
                                                    message: m.message })),
  });
}
console.log(JSON.stringify(reports, null, 1));
