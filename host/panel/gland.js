// The gland's deformed outer surface (three.js, vendored), coloured by how far each point moved from the rest shape
// (viridis, 0 to the largest displacement). Drawn only when the surface or the view changes: no animation loop.
import * as THREE from "./vendor/three/three.module.min.js";

// viridis at five stops (matplotlib's), interpolated linearly
const VIRIDIS = [[0.267, 0.005, 0.329], [0.229, 0.322, 0.546], [0.128, 0.567, 0.551], [0.369, 0.789, 0.383],
  [0.993, 0.906, 0.144]];

const SCALE_FLOOR_MM = 5;
// where the camera looks from (a unit vector): in front of the gland and a little above it
const VIEW_FROM = new THREE.Vector3(0, -80, 25).normalize();

function viridis(t) {
  const x = Math.min(1, Math.max(0, t)) * (VIRIDIS.length - 1);
  const i = Math.min(VIRIDIS.length - 2, Math.floor(x));
  const f = x - i;
  return VIRIDIS[i].map((c, k) => c + f * (VIRIDIS[i + 1][k] - c));
}

export class Gland {
  constructor(element) {
    this.element = element;
    this.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
    this.renderer.setClearColor(0xffffff);
    element.appendChild(this.renderer.domElement);
    this.scene = new THREE.Scene();
    this.camera = new THREE.PerspectiveCamera(35, 1, 1, 1000);
    this.scene.add(new THREE.AmbientLight(0xffffff, 1.2));
    const light = new THREE.DirectionalLight(0xffffff, 2.0);
    light.position.set(-60, -100, 120);
    this.scene.add(light);
    this.group = new THREE.Group();
    this.group.rotation.set(-Math.PI / 2.4, 0, Math.PI / 6);
    this.scene.add(this.group);
    this.mesh = null;
    this.rest = null;
    this.scaleMm = SCALE_FLOOR_MM;
    this.turnable();
    new ResizeObserver(() => this.resize()).observe(element);
    this.resize();
  }

  resize() {
    const width = this.element.clientWidth || 400;
    const height = this.element.clientHeight || 300;
    this.renderer.setSize(width, height, false);
    this.renderer.domElement.style.width = "100%";
    this.renderer.domElement.style.height = "100%";
    this.camera.aspect = width / height;
    this.camera.updateProjectionMatrix();
    this.draw();
  }

  turnable() {
    // drag with a mouse, a pen or a finger to turn the gland; arrow keys when it has the focus
    let last = null;
    const canvas = this.renderer.domElement;
    canvas.tabIndex = 0;
    canvas.setAttribute("aria-label", "the gland in 3D: drag or use the arrow keys to turn it");
    canvas.addEventListener("pointerdown", (event) => { last = [event.clientX, event.clientY];
      canvas.setPointerCapture(event.pointerId); });
    canvas.addEventListener("pointerup", () => { last = null; });
    canvas.addEventListener("pointermove", (event) => {
      if (!last) return;
      this.turn((event.clientX - last[0]) * 0.01, (event.clientY - last[1]) * 0.01);
      last = [event.clientX, event.clientY];
    });
    canvas.addEventListener("keydown", (event) => {
      const step = { ArrowLeft: [-0.2, 0], ArrowRight: [0.2, 0], ArrowUp: [0, -0.2], ArrowDown: [0, 0.2] }[event.key];
      if (step) { event.preventDefault(); this.turn(...step); }
    });
  }

  turn(aroundZ, aroundX) {
    this.group.rotation.z += aroundZ;
    this.group.rotation.x += aroundX;
    this.draw();
  }

  setRest(surface) {
    this.rest = surface.positions_mm;
  }

  // Show a surface {positions_mm, triangles}; returns the largest displacement from the rest shape (mm).
  show(surface) {
    const positions = surface.positions_mm;
    const count = positions.length;
    const xyz = new Float32Array(count * 3);
    const moved = new Float32Array(count);
    let largest = 0;
    for (let i = 0; i < count; i++) {
      const p = positions[i];
      xyz.set(p, i * 3);
      if (this.rest && this.rest.length === count) {
        const r = this.rest[i];
        moved[i] = Math.hypot(p[0] - r[0], p[1] - r[1], p[2] - r[2]);
        largest = Math.max(largest, moved[i]);
      }
    }
    // the colour scale's top: the largest displacement, but at least SCALE_FLOOR_MM, so that a gland near its rest
    // shape does not look as coloured as one grown by centimetres
    this.scaleMm = Math.max(largest, SCALE_FLOOR_MM);
    const colours = new Float32Array(count * 3);
    for (let i = 0; i < count; i++) colours.set(viridis(moved[i] / this.scaleMm), i * 3);
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute("position", new THREE.BufferAttribute(xyz, 3));
    geometry.setAttribute("color", new THREE.BufferAttribute(colours, 3));
    geometry.setIndex(surface.triangles.flat());
    geometry.computeVertexNormals();
    geometry.computeBoundingSphere();
    this.radius = geometry.boundingSphere.radius;
    if (this.mesh) {
      this.group.remove(this.mesh);
      this.mesh.geometry.dispose();
    } else {
      this.material = new THREE.MeshLambertMaterial({ vertexColors: true, side: THREE.DoubleSide });
    }
    this.mesh = new THREE.Mesh(geometry, this.material);
    this.mesh.position.copy(geometry.boundingSphere.center).multiplyScalar(-1); // turned about its centre
    this.group.add(this.mesh);
    this.draw();
    return largest;
  }

  draw() {
    // the camera as far as the gland needs to fill the view with a margin, whatever the view's shape
    const radius = this.radius || 25;
    const halfHeight = THREE.MathUtils.degToRad(this.camera.fov / 2);
    const halfWidth = Math.atan(Math.tan(halfHeight) * this.camera.aspect);
    const distance = (radius * 1.08) / Math.sin(Math.min(halfHeight, halfWidth));
    this.camera.position.copy(VIEW_FROM).multiplyScalar(distance);
    this.camera.lookAt(0, 0, 0);
    this.renderer.render(this.scene, this.camera);
  }
}
