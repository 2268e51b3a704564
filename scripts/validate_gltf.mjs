// Validate a glTF/GLB file with the Khronos glTF-Validator; prints its JSON report.
// Usage: node scripts/validate_gltf.mjs model.glb|model.gltf
// A .gltf file's buffers and images are read from its own folder (relative URIs only; nothing
// outside the folder, no absolute paths, no other schemes: those are reported as not loaded).
import { readFile } from "node:fs/promises";
import { dirname, resolve, sep } from "node:path";
import validator from "gltf-validator";

const path = process.argv[2];
const folder = resolve(dirname(path));
const data = new Uint8Array(await readFile(path));
const external = async (uri) => {
  const rel = decodeURIComponent(uri);
  const file = resolve(folder, rel);
  if (/^[a-z][a-z0-9+.-]*:/i.test(uri) || rel.startsWith("/") || !file.startsWith(folder + sep)) {
    throw new Error(`not a file in the document's folder: ${uri}`);
  }
  return new Uint8Array(await readFile(file));
};
const report = await validator.validateBytes(data, { uri: path, maxIssues: 100, externalResourceFunction: external });
process.stdout.write(JSON.stringify(report, null, 1) + "\n");
