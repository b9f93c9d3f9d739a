// Validate a .glb with the Khronos glTF validator and print its report as JSON.
// Usage: node validate_gltf.js <path/to/node_modules/gltf-validator> <file.glb>
"use strict";
const fs = require("fs");
const validator = require(require("path").resolve(process.argv[2]));
const data = new Uint8Array(fs.readFileSync(process.argv[3]));
validator.validateBytes(data, { maxIssues: 100, writeTimestamp: false })
  .then((report) => { console.log(JSON.stringify(report)); })
  .catch((error) => { console.error(String(error)); process.exit(1); });
