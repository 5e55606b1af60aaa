// Drives Niantic's SPZ library (the @adobe/spz WebAssembly build of github.com/nianticlabs/spz) for
// tests/seggaussian/io/test_spz_niantic.py: loads and saves SPZ files, exchanging the Gaussian cloud as raw
// little-endian float32 arrays.
//
//     node niantic_spz.mjs SPZ_MODULE JOBS_JSON
//
// SPZ_MODULE: path of @adobe/spz's dist/spz.js. JOBS_JSON: a JSON list of jobs, each
//   {"op": "load", "in": FILE.spz, "out": PREFIX, "to": FRAME}: Niantic's loadSpzFromBuffer with
//       UnpackOptions.to = FRAME (a CoordinateSystem name: RDF, RUB, UNSPECIFIED = no conversion); writes
//       PREFIX.json (numPoints, shDegree, antialiased) and PREFIX.<attribute>.f32 for positions, scales,
//       rotations (x, y, z, w), alphas (logits), colors (f_dc), sh (coefficient-major, channel innermost);
//   {"op": "save", "in": PREFIX, "out": FILE.spz, "version": V, "from": FRAME, "sh1Bits": B1,
//       "shRestBits": B2}: reads PREFIX.json and the PREFIX.<attribute>.f32 arrays, writes Niantic's
//       saveSpzToBuffer with PackOptions {version, from, sh1Bits, shRestBits}.
// The library logs to stdout; errors go to stderr with exit status 1.
import { readFileSync, writeFileSync } from 'node:fs';
import { pathToFileURL } from 'node:url';

const ATTRIBUTES = ['positions', 'scales', 'rotations', 'alphas', 'colors', 'sh'];

const [modulePath, jobsPath] = process.argv.slice(2);
const { default: createSpzModule } = await import(pathToFileURL(modulePath).href);
const spz = await createSpzModule();

const frame = (name) => {
    const value = spz.CoordinateSystem[name];
    if (value === undefined) throw new Error(`unknown coordinate system ${name}`);
    return value;
};

const readF32 = (path) => {
    const bytes = readFileSync(path);
    return new Float32Array(bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength));
};

for (const job of JSON.parse(readFileSync(jobsPath, 'utf8'))) {
    if (job.op === 'load') {
        const cloud = spz.loadSpzFromBuffer(new Uint8Array(readFileSync(job.in)), { to: frame(job.to) });
        if (!cloud || !(cloud.numPoints > 0)) throw new Error(`${job.in}: Niantic's loader returned no Gaussians`);
        writeFileSync(`${job.out}.json`, JSON.stringify({
            numPoints: cloud.numPoints, shDegree: cloud.shDegree, antialiased: cloud.antialiased
        }));
        for (const name of ATTRIBUTES) {
            const array = cloud[name];
            writeFileSync(`${job.out}.${name}.f32`, new Uint8Array(array.buffer, array.byteOffset, array.byteLength));
        }
    } else if (job.op === 'save') {
        const meta = JSON.parse(readFileSync(`${job.in}.json`, 'utf8'));
        const cloud = { ...meta, extensions: [] };
        for (const name of ATTRIBUTES) cloud[name] = readF32(`${job.in}.${name}.f32`);
        const bytes = spz.saveSpzToBuffer(cloud, {
            version: job.version, from: frame(job.from), sh1Bits: job.sh1Bits, shRestBits: job.shRestBits
        });
        if (!bytes || bytes.length === 0) throw new Error(`${job.out}: Niantic's writer returned no bytes`);
        writeFileSync(job.out, bytes);
    } else {
        throw new Error(`unknown op ${job.op}`);
    }
}
