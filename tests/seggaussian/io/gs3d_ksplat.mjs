// Drives GaussianSplats3D (@mkkellogg/gaussian-splats-3d, the author of the .ksplat format) headless in node
// for tests/seggaussian/io/test_ksplat_gs3d.py: its SplatBuffer decodes .ksplat files, its PlyLoader writes
// them from a 3DGS PLY (the path of its util/create-ksplat.js) and its SplatLoader reads antimatter15 .splat
// files, exchanging arrays as raw little-endian files.
//
//     node gs3d_ksplat.mjs GS3D_MODULE JOBS_JSON
//
// GS3D_MODULE: path of build/gaussian-splats-3d.module.js (three.js resolved beside it). JOBS_JSON: a list of
//   {"op": "decode", "in": FILE.ksplat, "out": PREFIX}: SplatBuffer fill* methods, no transform, level-0
//       (float) output: PREFIX.json (count, shDegree), PREFIX.centers.f32 [N, 3], PREFIX.scales.f32 [N, 3]
//       (linear), PREFIX.rotations.f32 [N, 4] (x, y, z, w; normalized, w >= 0), PREFIX.colors.u8 [N, 4]
//       (r, g, b, a), PREFIX.sh.f32 [N, 9 or 24] as SplatBuffer hands them to the renderer (coefficient-major,
//       channel innermost; level-2 bytes mapped to values with the file's SH range);
//   {"op": "encode", "in": FILE.ply, "out": FILE.ksplat, "level": L, "shDegree": D}: PlyLoader.loadFromFileData
//       with minimumAlpha 0 (keep every splat), optimizeSplatData true, written as the SplatBuffer's bytes;
//   {"op": "decode_splat", "in": FILE.splat, "out": PREFIX}: SplatLoader.loadFromFileData (its SplatParser; level
//       0, minimumAlpha 0, not reordered), then the same outputs as "decode".
// Errors go to stderr with exit status 1.
import { readFileSync, writeFileSync } from 'node:fs';
import { pathToFileURL } from 'node:url';

const [modulePath, jobsPath] = process.argv.slice(2);
// The loaders yield to the browser's event loop through window.setTimeout; node has the same function globally.
globalThis.window ??= globalThis;
const GS3D = await import(pathToFileURL(modulePath).href);
const SH_COMPONENTS = [0, 9, 24];

const arrayBufferOf = (path) => {
    const bytes = readFileSync(path);
    return bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength);
};
const write = (path, array) => writeFileSync(path, new Uint8Array(array.buffer, array.byteOffset, array.byteLength));

for (const job of JSON.parse(readFileSync(jobsPath, 'utf8'))) {
    if (job.op === 'decode' || job.op === 'decode_splat') {
        const buffer = job.op === 'decode' ? new GS3D.SplatBuffer(arrayBufferOf(job.in))
            : await GS3D.SplatLoader.loadFromFileData(arrayBufferOf(job.in), 0, 0, false);
        const n = buffer.getSplatCount();
        const degree = buffer.getMinSphericalHarmonicsDegree();
        const centers = new Float32Array(n * 3);
        const scales = new Float32Array(n * 3);
        const rotations = new Float32Array(n * 4);
        const colors = new Uint8Array(n * 4);
        const sh = new Float32Array(n * SH_COMPONENTS[degree]);
        buffer.fillSplatCenterArray(centers, undefined, 0, n - 1, 0);
        buffer.fillSplatScaleRotationArray(scales, rotations, undefined, 0, n - 1, 0, 0);
        buffer.fillSplatColorArray(colors, 0, 0, n - 1, 0);
        if (degree > 0) buffer.fillSphericalHarmonicsArray(sh, degree, undefined, 0, n - 1, 0, 0);
        if (buffer.compressionLevel === 2) {
            // level-2 SH come out as the stored bytes (the renderer's shader maps them); map them here as
            // SplatBuffer's fromUint8 does: min + b / 255 * (max - min)
            const min = buffer.minSphericalHarmonicsCoeff, max = buffer.maxSphericalHarmonicsCoeff;
            for (let i = 0; i < sh.length; i++) sh[i] = sh[i] / 255 * (max - min) + min;
        }
        writeFileSync(`${job.out}.json`, JSON.stringify({ count: n, shDegree: degree }));
        write(`${job.out}.centers.f32`, centers);
        write(`${job.out}.scales.f32`, scales);
        write(`${job.out}.rotations.f32`, rotations);
        write(`${job.out}.colors.u8`, colors);
        write(`${job.out}.sh.f32`, sh);
    } else if (job.op === 'encode') {
        const buffer = await GS3D.PlyLoader.loadFromFileData(arrayBufferOf(job.in), 0, job.level, true, job.shDegree);
        writeFileSync(job.out, new Uint8Array(buffer.bufferData));
    } else {
        throw new Error(`unknown op ${job.op}`);
    }
}
