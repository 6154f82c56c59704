// The escape room drawn with three.js: walls, the dotted start circle, the solid exit circle, the
// red button, the keys, one disc per trigger zone and the robot, from the protocol's floor plan.
//
// Kept cheap on purpose so that a lab's plain PC, a tablet and software rendering all draw it
// smoothly (bench/room.py measures the frame rate in headless Chromium): no lights, shadows or
// antialiasing; unlit materials, each wall's faces shaded by the way they face (a fixed "sun"),
// a few dozen meshes; and when frames still come slower than TARGET_FPS the canvas draws fewer
// pixels (the browser scales them up) until they do not.
//
// Room coordinates (x, z) map to three.js as (x - start.x, y, start.z - z): the start circle is
// the origin and the room's far wall lies ahead (-z), so a headset's reference space, whose
// origin is where the participant stands at the start, needs no further transform.

import * as THREE from "../../vendor/three/three.module.js";

const EYE_HEIGHT = 1.6;
const LOOK_DOWN = -0.12; // radians: the floor, its zones and circles a step ahead stay in view
const COLOURS = {
  head: 0xdfe4ea,
  floor: 0xe9e4da,
  wall: 0xb9c3cf,
  innerWall: 0x8d9aab,
  start: 0x2a7a4b,
  exit: 0x2a7a4b,
  zone: { pending: 0x6b8cc4, asked: 0xe0a100, done: 0x9aa3ad },
  button: 0xd0312d,
  keys: 0xe8b923,
  robot: 0xf2f4f7,
  robotTrim: 0x5b6b80,
  marker: 0x7a4bc4,
};

const TARGET_FPS = 36;
const MIN_PIXEL_RATIO = 0.5;
const SUN = new THREE.Vector3(0.45, 0.8, 0.4).normalize();

/** A flat, unlit material: the cheap kind (shading, where it matters, is baked in by shade()). */
function unlit(colour, extra = {}) {
  return new THREE.MeshBasicMaterial({ color: colour, ...extra });
}

/** A colour as lit by the fixed sun on a surface facing ``normal`` (computed once, not per pixel). */
function shade(colour, normal) {
  const light = 0.62 + 0.38 * Math.max(0, normal.dot(SUN));
  return new THREE.Color(colour).multiplyScalar(light);
}

/** Six materials for a box's faces (+x, -x, +y, -y, +z, -z of the box) rotated by ``yaw``. */
function boxFaces(colour, yaw) {
  const rotation = new THREE.Euler(0, yaw, 0);
  const normals = [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]];
  return normals.map(([x, y, z]) => {
    const normal = new THREE.Vector3(x, y, z).applyEuler(rotation);
    return new THREE.MeshBasicMaterial({ color: shade(colour, normal) });
  });
}

function ring(inner, outer, colour, segments = 48, thetaStart = 0, thetaLength = Math.PI * 2) {
  const geometry = new THREE.RingGeometry(inner, outer, segments, 1, thetaStart, thetaLength);
  const mesh = new THREE.Mesh(geometry, new THREE.MeshBasicMaterial({ color: colour, side: THREE.DoubleSide }));
  mesh.rotation.x = -Math.PI / 2;
  return mesh;
}

function dottedRing(radius, colour) {
  const group = new THREE.Group();
  const dashes = 16;
  for (let i = 0; i < dashes; i += 1) {
    const arc = ring(radius - 0.05, radius, colour, 6, (i * 2 * Math.PI) / dashes, Math.PI / dashes);
    group.add(arc);
  }
  return group;
}

/** A robot that turns to face the participant: a body, a head and two eyes (or, for a physical
 * robot standing in the room, a marker post showing where it stands). */
function robotFigure(style) {
  const group = new THREE.Group();
  if (style === "marker") {
    const post = new THREE.Mesh(new THREE.CylinderGeometry(0.05, 0.05, 1.2, 12), unlit(COLOURS.marker));
    post.position.y = 0.6;
    group.add(post);
    const base = ring(0.25, 0.35, COLOURS.marker);
    base.position.y = 0.01;
    group.add(base);
    return group;
  }
  const body = new THREE.Mesh(new THREE.CylinderGeometry(0.22, 0.3, 0.8, 16), unlit(COLOURS.robot));
  body.position.y = 0.4;
  const head = new THREE.Mesh(new THREE.SphereGeometry(0.2, 16, 12), unlit(COLOURS.head));
  head.position.y = 1.0;
  const eyeMaterial = unlit(COLOURS.robotTrim);
  for (const side of [-1, 1]) {
    const eye = new THREE.Mesh(new THREE.SphereGeometry(0.035, 8, 6), eyeMaterial);
    eye.position.set(side * 0.07, 1.04, 0.18); // +z of the figure is its face
    group.add(eye);
  }
  const belt = new THREE.Mesh(new THREE.TorusGeometry(0.26, 0.025, 6, 20), eyeMaterial);
  belt.rotation.x = Math.PI / 2;
  belt.position.y = 0.55;
  group.add(body, head, belt);
  return group;
}

export class RoomScene {
  /**
   * @param {HTMLElement} host where the canvas goes
   * @param {object} layout the protocol's floor plan (GET /api/v1/station/room → layout)
   * @param {{robot?: string, scale?: number}} options ``robot: "marker"`` draws a marker for a
   *   physical robot; ``scale`` pins the pixels drawn per CSS pixel (no adapting to the frame rate)
   */
  constructor(host, layout, options = {}) {
    this.layout = layout;
    this.renderer = new THREE.WebGLRenderer({ antialias: false, powerPreference: "low-power" });
    this.maxPixelRatio = Math.min(window.devicePixelRatio || 1, 1.5);
    this.fixedScale = Number.isFinite(options.scale) && options.scale > 0 ? options.scale : null;
    this.renderer.setPixelRatio(this.fixedScale ?? this.maxPixelRatio);
    this.renderer.xr.enabled = true;
    this.renderer.xr.setReferenceSpaceType("local-floor");
    host.appendChild(this.renderer.domElement);
    this.host = host;

    this.scene = new THREE.Scene();
    this.background = new THREE.Color(0xdfe7ef);
    this.scene.background = this.background;
    this.camera = new THREE.PerspectiveCamera(70, 1, 0.05, 100);

    this.world = new THREE.Group();
    this.world.position.set(-layout.start.x, 0, layout.start.z);
    this.scene.add(this.world);
    this.zones = new Map();
    this._build(options);
    this.resize();
  }

  /** A point of the room in the world group's frame. */
  _at(x, z, y = 0) {
    return new THREE.Vector3(x, y, -z);
  }

  _build(options) {
    const { layout } = this;
    const floor = new THREE.Mesh(new THREE.PlaneGeometry(layout.width, layout.depth), unlit(COLOURS.floor));
    floor.rotation.x = -Math.PI / 2;
    floor.position.copy(this._at(layout.width / 2, layout.depth / 2));
    this.world.add(floor);

    const height = layout.wall_height;
    const outer = [
      [0, 0, layout.width, 0],
      [layout.width, 0, layout.width, layout.depth],
      [layout.width, layout.depth, 0, layout.depth],
      [0, layout.depth, 0, 0],
    ];
    for (const [x1, z1, x2, z2] of outer) this._wall(x1, z1, x2, z2, height, COLOURS.wall);
    for (const wall of layout.walls) this._wall(wall.x1, wall.z1, wall.x2, wall.z2, height, COLOURS.innerWall);
    const grid = new THREE.GridHelper(Math.max(layout.width, layout.depth), Math.ceil(Math.max(layout.width, layout.depth)), 0xcfc8ba, 0xcfc8ba);
    grid.position.copy(this._at(layout.width / 2, layout.depth / 2, 0.005));
    grid.scale.set(layout.width / Math.max(layout.width, layout.depth), 1, layout.depth / Math.max(layout.width, layout.depth));
    this.world.add(grid);

    const start = dottedRing(layout.start.radius, COLOURS.start);
    start.position.copy(this._at(layout.start.x, layout.start.z, 0.01));
    const exit = ring(layout.exit.radius - 0.09, layout.exit.radius, COLOURS.exit);
    exit.position.copy(this._at(layout.exit.x, layout.exit.z, 0.01));
    this.world.add(start, exit);

    for (const zone of layout.zones) {
      const disc = new THREE.Mesh(
        new THREE.CircleGeometry(zone.radius, 40),
        new THREE.MeshBasicMaterial({ color: COLOURS.zone.pending, transparent: true, opacity: 0.35 }),
      );
      disc.rotation.x = -Math.PI / 2;
      disc.position.copy(this._at(zone.x, zone.z, 0.015));
      this.world.add(disc);
      this.zones.set(zone.category, disc);
    }

    const button = new THREE.Group();
    const plate = new THREE.Mesh(new THREE.BoxGeometry(0.3, 0.3, 0.05), unlit(0x444b55));
    const knob = new THREE.Mesh(new THREE.CylinderGeometry(0.09, 0.09, 0.08, 20), unlit(COLOURS.button));
    knob.rotation.x = Math.PI / 2;
    knob.position.z = 0.05;
    button.add(plate, knob);
    button.position.copy(this._at(layout.red_button.x, layout.red_button.z, 1.1));
    button.lookAt(this._at(layout.width / 2, layout.depth / 2, 1.1).add(this.world.position));
    this.world.add(button);

    if (layout.keys) {
      const keyMaterial = unlit(COLOURS.keys);
      const keys = new THREE.Group();
      for (let i = 0; i < 4; i += 1) {
        const key = new THREE.Mesh(new THREE.BoxGeometry(0.05, 0.02, 0.18), keyMaterial);
        key.position.set((i - 1.5) * 0.09, 0, 0);
        keys.add(key);
      }
      const table = new THREE.Mesh(new THREE.BoxGeometry(0.5, 0.8, 0.4), unlit(0x8a6f4d));
      table.position.y = -0.41;
      keys.add(table);
      keys.position.copy(this._at(layout.keys.x, layout.keys.z, 0.82));
      this.world.add(keys);
    }

    this.robot = robotFigure(options.robot);
    this.robot.position.copy(this._at(layout.robot.x, layout.robot.z));
    this.world.add(this.robot);
  }

  _wall(x1, z1, x2, z2, height, colour) {
    const length = Math.hypot(x2 - x1, z2 - z1);
    const yaw = Math.atan2(z2 - z1, x2 - x1); // room z runs along three's -z
    const wall = new THREE.Mesh(new THREE.BoxGeometry(length + 0.12, height, 0.12), boxFaces(colour, yaw));
    wall.position.copy(this._at((x1 + x2) / 2, (z1 + z2) / 2, height / 2));
    wall.rotation.y = yaw;
    this.world.add(wall);
  }

  /** Colour a zone by where its category stands in the run: pending, asked or done. */
  setZoneState(category, state) {
    const disc = this.zones.get(category);
    if (!disc) return;
    disc.material.color.setHex(COLOURS.zone[state] ?? COLOURS.zone.pending);
    disc.material.opacity = state === "done" ? 0.18 : 0.35;
  }

  /** Place the camera at the participant's pose (outside a headset session) and turn the robot
   * to face them. */
  update(pose) {
    if (!this.renderer.xr.isPresenting) {
      const eye = this._at(pose.x, pose.z, EYE_HEIGHT).add(this.world.position);
      this.camera.position.copy(eye);
      this.camera.rotation.set(LOOK_DOWN, (-pose.heading * Math.PI) / 180, 0, "YXZ");
    }
    const dx = pose.x - this.layout.robot.x;
    const dz = pose.z - this.layout.robot.z;
    this.robot.rotation.y = Math.atan2(dx, -dz); // its face (+z) towards the participant
  }

  /** Where a headset's camera is, in its reference space, and which way it looks. */
  headsetView() {
    const camera = this.renderer.xr.getCamera();
    const direction = new THREE.Vector3();
    camera.getWorldDirection(direction);
    return { position: camera.position, direction };
  }

  resize() {
    const width = this.host.clientWidth || 1;
    const height = this.host.clientHeight || 1;
    this.camera.aspect = width / height;
    this.camera.updateProjectionMatrix();
    this.renderer.setSize(width, height, false);
  }

  /** Draw every frame by calling ``frame(seconds)`` first (works in and out of a headset). */
  start(frame) {
    let last = performance.now();
    let windowStart = last;
    let windowFrames = 0;
    this.renderer.setAnimationLoop((now) => {
      const seconds = (now - last) / 1000;
      last = now;
      frame(seconds);
      this.renderer.render(this.scene, this.camera);
      windowFrames += 1;
      if (now - windowStart >= 1000) {
        this._adapt((windowFrames * 1000) / (now - windowStart));
        windowStart = now;
        windowFrames = 0;
      }
    });
  }

  /** Fewer pixels while frames are slow, back towards the screen's own when they are fast. */
  _adapt(fps) {
    if (this.renderer.xr.isPresenting || this.fixedScale) return; // the headset's own, or pinned
    const ratio = this.renderer.getPixelRatio();
    let next = ratio;
    if (fps < TARGET_FPS && ratio > MIN_PIXEL_RATIO) next = Math.max(MIN_PIXEL_RATIO, ratio * 0.8);
    else if (fps > TARGET_FPS * 1.5 && ratio < this.maxPixelRatio) next = Math.min(this.maxPixelRatio, ratio * 1.1);
    if (next !== ratio) {
      this.renderer.setPixelRatio(next);
      this.resize();
    }
  }

  /** Stop drawing and free the GPU's memory. */
  dispose() {
    this.renderer.setAnimationLoop(null);
    this.renderer.dispose();
    this.host.replaceChildren();
  }

  /** Pixels drawn per CSS pixel right now (below 1 when the frame rate asked for fewer). */
  get renderScale() {
    return this.renderer.getPixelRatio();
  }

  /** Start an immersive WebXR session (``immersive-ar`` or ``immersive-vr``); in passthrough AR
   * the drawn floor and walls fade so that the real room shows through. */
  async enterHeadset(mode, overlay) {
    const options = { optionalFeatures: ["local-floor", "dom-overlay"] };
    if (overlay) options.domOverlay = { root: overlay };
    const session = await navigator.xr.requestSession(mode, options);
    if (mode === "immersive-ar") this.scene.background = null;
    session.addEventListener("end", () => {
      this.scene.background = this.background;
    });
    await this.renderer.xr.setSession(session);
    return session;
  }
}

/** Whether this browser can draw WebGL at all (else the page says so instead of a blank room). */
export function webglAvailable() {
  try {
    const canvas = document.createElement("canvas");
    return Boolean(canvas.getContext("webgl2") || canvas.getContext("webgl"));
  } catch {
    return false;
  }
}
