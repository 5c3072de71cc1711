// node validate.cjs FILE.glb -> the Khronos glTF-Validator's report (JSON) on stdout.
const fs = require('fs');
const validator = require('gltf-validator');
const path = process.argv[2];
validator.validateBytes(new Uint8Array(fs.readFileSync(path)), { uri: path, maxIssues: 200 })
  .then((report) => { process.stdout.write(JSON.stringify(report)); })
  .catch((err) => { console.error(String(err)); process.exit(1); });
