// Validates a glTF or GLB with the Khronos glTF validator (npm
// `gltf-validator`, found through NODE_PATH); its files are read from beside
// it. Prints {errors, warnings, error_codes, messages} as JSON (error_codes:
// how many errors of each code; messages: the errors and warnings, at most
// eight).
const fs = require('fs'); const path = require('path');
const validator = require('gltf-validator');
const file = process.argv[2];
const dir = path.dirname(file);
validator.validateBytes(new Uint8Array(fs.readFileSync(file)), {
  uri: path.basename(file),
  externalResourceFunction: (uri) => new Promise((res, rej) => {
    try { res(new Uint8Array(fs.readFileSync(path.join(dir, decodeURIComponent(uri))))); } catch (e) { rej(e.toString()); }
  }),
}).then((r) => {
  const codes = {};
  for (const m of r.issues.messages.filter(m => m.severity === 0)) codes[m.code] = (codes[m.code] || 0) + 1;
  console.log(JSON.stringify({errors: r.issues.numErrors, warnings: r.issues.numWarnings, error_codes: codes, messages: r.issues.messages.filter(m => m.severity <= 1).slice(0, 8).map(m => [m.severity, m.code, m.message, m.pointer])}));
}).catch((e) => { console.error(e); process.exit(1); });
