// An independent reader of a recording: the MCAP project's TypeScript reader through the
// file's index, every protobuf message decoded from the FileDescriptorSet its schema stores
// (protobufjs), as Foxglove opens a file. Prints, per topic, the schema, the message count
// and what the 3D and Image panels resolve: frames, transforms' ends, calibration matrices,
// the cloud's pose, the scene entities.
//
//   node tests/service/mcap_reader.mjs FILE.mcap     (after: npm install --prefix tests/service/node)
import { createRequire } from "node:module";
import { readFile } from "node:fs/promises";

const require = createRequire(new URL("./node/package.json", import.meta.url));
const { McapIndexedReader } = await import(require.resolve("@mcap/core"));
const { decompress: zstd } = require("fzstd");
const lz4 = require("lz4js");
const protobuf = require("protobufjs");
require("protobufjs/ext/descriptor");

const bytes = new Uint8Array(await readFile(process.argv[2]));
const readable = {
  size: async () => BigInt(bytes.length),
  read: async (offset, size) => bytes.subarray(Number(offset), Number(offset + size)),
};
const reader = await McapIndexedReader.Initialize({
  readable,
  decompressHandlers: {
    zstd: (data, size) => zstd(data, new Uint8Array(Number(size))),
    lz4: (data) => lz4.decompress(data),
  },
});

const types = new Map();
for (const [id, schema] of reader.schemasById) {
  if (schema.encoding !== "protobuf") continue;
  const set = protobuf.descriptor.FileDescriptorSet.decode(schema.data);
  types.set(id, protobuf.Root.fromDescriptor(set).lookupType(schema.name));
}

const pick = (m) => {
  const seen = {};
  for (const key of ["frame_id", "parent_frame_id", "child_frame_id", "R", "P", "level"]) {
    if (m[key] !== undefined) seen[key] = m[key];
  }
  if (m.pose !== undefined) seen.pose = m.pose;
  if (m.entities !== undefined) {
    seen.entities = m.entities.map((e) => [e.id, e.frame_id, (e.triangles ?? []).length]);
  }
  return seen;
};

const out = {};
for await (const message of reader.readMessages()) {
  const channel = reader.channelsById.get(message.channelId);
  const schema = reader.schemasById.get(channel.schemaId);
  const entry = (out[channel.topic] ??= { schema: schema.name, count: 0, first: null });
  entry.count += 1;
  let decoded;
  if (channel.messageEncoding === "protobuf") {
    const type = types.get(channel.schemaId);
    decoded = type.toObject(type.decode(message.data), { longs: Number, defaults: true });
  } else {
    decoded = JSON.parse(new TextDecoder().decode(message.data));
  }
  entry.first ??= pick(decoded);
}
process.stdout.write(JSON.stringify(out));
