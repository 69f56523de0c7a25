// Validate glTF files with the Khronos glTF validator (npm gltf-validator); prints one JSON
// report per file. Usage: node gltf_validate.mjs FILE... ; module directory in
// GLTF_VALIDATOR_DIR (node_modules parent). External resources (images) are read from disk
// relative to each file, so missing or broken PNGs are reported too.
import { readFileSync } from 'node:fs';
import { createRequire } from 'node:module';
import { dirname, join, resolve } from 'node:path';

const base = process.env.GLTF_VALIDATOR_DIR;
const validator = createRequire(join(resolve(base), 'noop.js'))('gltf-validator');

const reports = [];
for (const file of process.argv.slice(2)) {
	const dir = dirname(resolve(file));
	const report = await validator.validateBytes(new Uint8Array(readFileSync(file)), {
		uri: file,
		maxIssues: 0,
		externalResourceFunction: (uri) =>
			new Promise((ok, fail) => {
				try {
					ok(new Uint8Array(readFileSync(join(dir, decodeURIComponent(uri)))));
				} catch (e) {
					fail(e.toString());
				}
			}),
	});
	reports.push(report);
}
process.stdout.write(JSON.stringify(reports));
