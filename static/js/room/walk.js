// Walking through the escape room: poses, collisions with the walls, zones and circles.
//
// Pure geometry on the protocol's floor plan (app/room.py): metres, x from the left wall, z from
// the near wall, a heading in degrees with 0 facing the far wall and 90 the right wall. No DOM and
// no three.js here, so the rules of movement are the same on a screen, a tablet and in a headset.

export const WALK_SPEED = 1.4; // metres a second: a calm indoor walk
export const TURN_SPEED = 110; // degrees a second
export const BODY_RADIUS = 0.25; // how close the participant's centre gets to a wall
export const WALL_THICKNESS = 0.12;
const SUB_STEP = 0.05; // metres per collision check: never walks through a wall
const MAX_FRAME = 0.1; // seconds: a stalled frame does not jump the participant

/** The pose a run starts in: the centre of the start circle, facing the far wall. */
export function startPose(layout) {
  return { x: layout.start.x, z: layout.start.z, heading: 0 };
}

/** The unit vector a heading looks along, in room coordinates. */
export function forward(heading) {
  const radians = (heading * Math.PI) / 180;
  return { x: Math.sin(radians), z: Math.cos(radians) };
}

/** A heading folded into [0, 360). */
export function normaliseHeading(heading) {
  return ((heading % 360) + 360) % 360;
}

/** The heading that looks from (x, z) towards (tx, tz). */
export function headingTowards(x, z, tx, tz) {
  return normaliseHeading((Math.atan2(tx - x, tz - z) * 180) / Math.PI);
}

/** Every wall as a segment: the four outer walls, then the protocol's inner walls. */
export function wallSegments(layout) {
  const { width: w, depth: d } = layout;
  const outer = [
    { x1: 0, z1: 0, x2: w, z2: 0 },
    { x1: w, z1: 0, x2: w, z2: d },
    { x1: w, z1: d, x2: 0, z2: d },
    { x1: 0, z1: d, x2: 0, z2: 0 },
  ];
  return outer.concat(layout.walls.map((wall) => ({ ...wall })));
}

function closestOnSegment(x, z, s) {
  const dx = s.x2 - s.x1;
  const dz = s.z2 - s.z1;
  const length2 = dx * dx + dz * dz;
  const t = length2 > 0 ? Math.max(0, Math.min(1, ((x - s.x1) * dx + (z - s.z1) * dz) / length2)) : 0;
  return { x: s.x1 + t * dx, z: s.z1 + t * dz };
}

/** (x, z) pushed out of every wall it is too close to, so the participant slides along walls
 * instead of stopping dead or passing through them. */
export function resolveCollisions(segments, x, z, radius = BODY_RADIUS) {
  const clearance = radius + WALL_THICKNESS / 2;
  for (let pass = 0; pass < 3; pass += 1) {
    let moved = false;
    for (const segment of segments) {
      const near = closestOnSegment(x, z, segment);
      const dx = x - near.x;
      const dz = z - near.z;
      const distance = Math.hypot(dx, dz);
      if (distance < clearance) {
        if (distance > 1e-9) {
          x = near.x + (dx / distance) * clearance;
          z = near.z + (dz / distance) * clearance;
        } else {
          // exactly on the wall's line: step back along the wall's normal
          const sx = segment.x2 - segment.x1;
          const sz = segment.z2 - segment.z1;
          const length = Math.hypot(sx, sz) || 1;
          x = near.x - (sz / length) * clearance;
          z = near.z + (sx / length) * clearance;
        }
        moved = true;
      }
    }
    if (!moved) break;
  }
  return { x, z };
}

/**
 * The pose after ``seconds`` of input: ``input.forward`` (-1 back … 1 ahead), ``input.strafe``
 * (-1 left … 1 right) and ``input.turn`` (-1 left … 1 right), each scaled by the speeds above.
 * The move is split into short sub-steps, each checked against the walls.
 */
export function step(layout, segments, pose, input, seconds) {
  const dt = Math.max(0, Math.min(seconds, MAX_FRAME));
  const heading = normaliseHeading(pose.heading + (input.turn || 0) * TURN_SPEED * dt);
  const ahead = forward(heading);
  const right = { x: ahead.z, z: -ahead.x };
  const along = (input.forward || 0) * WALK_SPEED * dt;
  const aside = (input.strafe || 0) * WALK_SPEED * dt;
  const dx = ahead.x * along + right.x * aside;
  const dz = ahead.z * along + right.z * aside;
  const distance = Math.hypot(dx, dz);
  const count = Math.max(1, Math.ceil(distance / SUB_STEP));
  let { x, z } = pose;
  for (let i = 0; i < count; i += 1) {
    ({ x, z } = resolveCollisions(segments, x + dx / count, z + dz / count));
  }
  return { x, z, heading };
}

/** Whether (x, z) lies inside a circle of the plan (a zone, the start or the exit). */
export function inside(circle, x, z) {
  return Math.hypot(x - circle.x, z - circle.z) <= circle.radius;
}

/** The trigger zone (x, z) stands in, or null (zones never overlap: app/room.py refuses it). */
export function zoneAt(layout, x, z) {
  return layout.zones.find((zone) => inside(zone, x, z)) || null;
}

/**
 * The room pose of a headset, from the camera's position and viewing direction in the WebXR
 * reference space. The room is drawn so that the space's origin is the start circle's centre and
 * its forward direction (-z in three.js) is the room's +z: walking ahead in the lab walks up the
 * first corridor.
 */
export function poseFromHeadset(layout, position, direction) {
  return {
    x: layout.start.x + position.x,
    z: layout.start.z - position.z,
    heading: normaliseHeading((Math.atan2(direction.x, -direction.z) * 180) / Math.PI),
  };
}
