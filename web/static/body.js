// The textured body (body.glb from `tbp texture`: glTF binary in metres, the scan's mesh with
// a texture atlas) as a three.js mesh in the viewer's millimetres.
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
