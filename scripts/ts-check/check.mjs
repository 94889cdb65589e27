// Decodes every message of microstereo recordings with the TypeScript readers Foxglove
// uses (@mcap/core, @foxglove/rosmsg, @foxglove/rosmsg2-serialization) and checks what
// Foxglove needs to draw them: every Image beside a CameraInfo with the same stamps, a
// PointCloud2 with packed rgb, a MarkerArray and /tf_static with the cameras' frames.
// Usage: node check.mjs FILE.mcap [FILE.mcap ...]; exit 0 when all holds.
import { McapStreamReader } from "@mcap/core";
import { parse } from "@foxglove/rosmsg";
import { MessageReader } from "@foxglove/rosmsg2-serialization";
import { decompress } from "fzstd";
import { readFileSync } from "node:fs";

function check(path) {
  const reader = new McapStreamReader({
    decompressHandlers: { zstd: (buf) => decompress(buf) },
  });
  reader.append(readFileSync(path));
  const schemas = new Map();
  const channels = new Map();
  const readers = new Map();
  const counts = new Map();
  const stamps = new Map();
  const problems = [];
  let tf = [];
  let decoded = 0;
  for (let rec; (rec = reader.nextRecord()); ) {
    if (rec.type === "Schema") schemas.set(rec.id, rec);
    else if (rec.type === "Channel") channels.set(rec.id, rec);
    else if (rec.type === "Message") {
      const ch = channels.get(rec.channelId);
      const schema = schemas.get(ch.schemaId);
      let r = readers.get(schema.id);
      if (!r) {
        const text = new TextDecoder().decode(schema.data);
        r = new MessageReader(parse(text, { ros2: true }));
        readers.set(schema.id, r);
      }
      let msg;
      try {
        msg = r.readMessage(rec.data);
        decoded += 1;
      } catch (e) {
        problems.push(`${ch.topic}: ${e}`);
        continue;
      }
      const key = `${ch.topic} ${schema.name}`;
      counts.set(key, (counts.get(key) ?? 0) + 1);
      if (msg.header) {
        const s = `${msg.header.stamp.sec}.${msg.header.stamp.nanosec}`;
        if (!stamps.has(ch.topic)) stamps.set(ch.topic, []);
        stamps.get(ch.topic).push(s);
      }
      if (schema.name === "tf2_msgs/msg/TFMessage") tf = msg.transforms.map((t) => t.child_frame_id);
      if (schema.name === "sensor_msgs/msg/PointCloud2") {
        const rgb = msg.fields.find((f) => f.name === "rgb");
        if (!rgb || rgb.datatype !== 7) problems.push(`${ch.topic}: no packed rgb`);
      }
    }
  }
  for (const [topic, s] of stamps) {
    if (!topic.endsWith("/image")) continue;
    const info = stamps.get(topic.slice(0, -"image".length) + "camera_info");
    if (!info || info.join() !== s.join()) problems.push(`${topic}: no CameraInfo with its stamps`);
  }
  for (const f of ["left_camera_optical_frame", "right_camera_optical_frame"]) {
    if (!tf.includes(f)) problems.push(`/tf_static lacks ${f}`);
  }
  if (![...counts.keys()].some((k) => k.endsWith("visualization_msgs/msg/MarkerArray")))
    problems.push("no MarkerArray");
  console.log(`${path}: ${decoded} messages on ${counts.size} channels decoded by @mcap/core + @foxglove/rosmsg2-serialization`);
  for (const p of problems.slice(0, 20)) console.log(`  PROBLEM: ${p}`);
  return decoded > 0 && problems.length === 0;
}

const results = process.argv.slice(2).map(check);
process.exit(results.length > 0 && results.every(Boolean) ? 0 : 1);
