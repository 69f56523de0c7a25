// Dump KTX2 files as JSON with npm's ktx-parse (an independent reader for the Python tests).
// Usage: node ktx_dump.mjs FILE... ; module directory in KTX_PARSE_DIR (node_modules parent).
import { readFileSync } from 'node:fs';
import { createRequire } from 'node:module';
import { join } from 'node:path';
import { pathToFileURL } from 'node:url';

const base = process.env.KTX_PARSE_DIR;
const entry = createRequire(join(base, 'noop.js')).resolve('ktx-parse');
const { read, write } = await import(pathToFileURL(entry).href);

const out = [];
for (const file of process.argv.slice(2)) {
	const bytes = new Uint8Array(readFileSync(file));
	const c = read(bytes);
	const keyValue = {};
	for (const [k, v] of Object.entries(c.keyValue)) {
		keyValue[k] = typeof v === 'string' ? { text: v } : { base64: Buffer.from(v).toString('base64') };
	}
	const rewritten = write(c, { keepWriter: true });
	out.push({
		file,
		vkFormat: c.vkFormat, typeSize: c.typeSize,
		pixelWidth: c.pixelWidth, pixelHeight: c.pixelHeight, pixelDepth: c.pixelDepth,
		layerCount: c.layerCount, faceCount: c.faceCount, levelCount: c.levelCount,
		supercompressionScheme: c.supercompressionScheme,
		dfd: c.dataFormatDescriptor[0],
		keyValue,
		levels: c.levels.map((l) => ({
			byteLength: l.levelData.byteLength,
			uncompressedByteLength: l.uncompressedByteLength,
			base64: Buffer.from(l.levelData).toString('base64'),
		})),
		rewriteIdentical: rewritten.byteLength === bytes.byteLength
			&& Buffer.compare(Buffer.from(rewritten), Buffer.from(bytes)) === 0,
	});
}
process.stdout.write(JSON.stringify(out));
