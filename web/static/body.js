// The textured body (body.glb from `tbp texture`: glTF binary in metres, the scan's mesh with
// a texture atlas) as a three.js mesh in the viewer's millimetres. The viewer loads the preview
// first (the same glTF with its atlas scaled down, /body?texture=preview) and then swaps in the
// full atlas (/body/texture) with its mipmaps (/body/texture/mipmaps), decoded off the main thread.
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";

// response: a fetch() Response for /api/scans/<folder>/body. Resolves to the mesh, or null when
// the scan has no textured body (404); rejects on any other failure.
export async function loadBody(response) {
  if (response.status === 404) return null;
  if (!response.ok) {
    const body = await response.json().catch(() => ({}));
    throw new Error(body.error ? body.error.message : `textured body: ${response.statusText}`);
  }
  const buffer = await response.arrayBuffer();
  const gltf = await new GLTFLoader().parseAsync(buffer, "");
  let mesh = null;
  gltf.scene.traverse((o) => { if (!mesh && o.isMesh) mesh = o; });
  if (!mesh) throw new Error("textured body: no mesh in body.glb");
  mesh.removeFromParent();
  mesh.geometry.scale(1000, 1000, 1000); // metres -> the viewer's mm (the same frame as the scan's mesh)
  mesh.geometry.computeVertexNormals();
  mesh.geometry.computeBoundingBox();
  mesh.geometry.computeBoundingSphere();
  mesh.material.side = THREE.FrontSide;
  return mesh;
}

// response: a promise of the fetch() Response for /api/scans/<folder>/body/texture (the full
// atlas). Resolves to it decoded (an ImageBitmap: Chromium decodes it off the main thread).
export async function decodeAtlas(response) {
  const answer = await response;
  if (!answer.ok) {
    const body = await answer.json().catch(() => ({}));
    throw new Error(body.error ? body.error.message : `full texture: ${answer.statusText}`);
  }
  return createImageBitmap(await answer.blob(), { premultiplyAlpha: "none" });
}

// response: a promise of the fetch() Response for /api/scans/<folder>/body/texture/mipmaps (the
// full atlas' mipmap levels 1, 2, ... on one JPEG sheet, where each lies in its Tbp-Mipmap-Levels
// header). Resolves to the levels, each an ImageBitmap cut from the decoded sheet.
export async function decodeMipmaps(response) {
  const answer = await response;
  if (!answer.ok) {
    const body = await answer.json().catch(() => ({}));
    throw new Error(body.error ? body.error.message : `texture mipmaps: ${answer.statusText}`);
  }
  const levels = JSON.parse(answer.headers.get("Tbp-Mipmap-Levels"));
  const sheet = await createImageBitmap(await answer.blob(), { premultiplyAlpha: "none" });
  const cut = await Promise.all(levels.map(([x, y, w, h]) => createImageBitmap(sheet, x, y, w, h, { premultiplyAlpha: "none" })));
  sheet.close();
  return cut;
}

// Replaces the preview's texture of the mesh with the decoded full atlas, made as GLTFLoader
// made the preview's (an ImageBitmap, not flipped; the same colour space, filters and wrapping).
// mipmaps: the atlas' levels 1, 2, ... (decodeMipmaps), uploaded with it, so the browser does not
// build the chain (a software renderer builds it in the frame that uploads the atlas).
export function swapInAtlas(mesh, bitmap, mipmaps) {
  const preview = mesh.material.map;
  const texture = new THREE.Texture(bitmap);
  for (const key of ["flipY", "colorSpace", "magFilter", "minFilter", "wrapS", "wrapT", "anisotropy"]) texture[key] = preview[key];
  texture.mipmaps = [bitmap, ...mipmaps];
  texture.generateMipmaps = false;
  texture.needsUpdate = true;
  mesh.material.map = texture;
  mesh.material.needsUpdate = true;
  preview.dispose();
  if (preview.image.close) preview.image.close();
}
