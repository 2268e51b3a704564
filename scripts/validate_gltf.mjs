// Validate a glTF/GLB file with the Khronos glTF-Validator; prints its JSON report.
// Usage: node scripts/validate_gltf.mjs model.glb
import { readFile } from "node:fs/promises";
import validator from "gltf-validator";

const path = process.argv[2];
const data = new Uint8Array(await readFile(path));
const report = await validator.validateBytes(data, { uri: path, maxIssues: 100 });
process.stdout.write(JSON.stringify(report, null, 1) + "\n");
