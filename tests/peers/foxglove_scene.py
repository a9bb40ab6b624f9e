"""A reader we did not write, on the world in a rigbridge run log: PyPI's `mcap` with
`mcap-protobuf-support` decodes every `/scene` message (protobuf foxglove.SceneUpdate) and
replays them as Foxglove's 3D panel would (a deletion of type ALL clears every entity, an
entity replaces the one of the same id).

Usage: foxglove_scene.py LOG.mcap
Prints one JSON object: the schema name, the message count, the paint area after each
message (m2, summed over the paint triangles, in log-time order), every paint point at the
end, and the entities at the end: per entity its frame, triangle area, triangle count, line loops (each a list of
points) and cylinders (centre, size, orientation). Driven by tests/foxglove.rs.
"""
import json
import sys

from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory


def triangle_area(points):
    area = 0.0
    for i in range(0, len(points) - 2, 3):
        a, b, c = points[i], points[i + 1], points[i + 2]
        u = (b.x - a.x, b.y - a.y, b.z - a.z)
        v = (c.x - a.x, c.y - a.y, c.z - a.z)
        cross = (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])
        area += 0.5 * sum(x * x for x in cross) ** 0.5
    return area


def paint_area(entities):
    return sum(
        triangle_area(t.points)
        for id_, e in entities.items()
        if id_.startswith("paint-")
        for t in e.triangles
    )


def main():
    path = sys.argv[1]
    factory = DecoderFactory()
    decoder = None
    entities = {}
    schema_name = None
    count = 0
    areas = []
    with open(path, "rb") as stream:
        for schema, channel, message in make_reader(stream).iter_messages(log_time_order=True):
            if channel.topic != "/scene":
                continue
            schema_name = schema.name
            if decoder is None:
                decoder = factory.decoder_for(channel.message_encoding, schema)
            update = decoder(message.data)
            count += 1
            for deletion in update.deletions:
                if deletion.type == 1:  # ALL
                    entities.clear()
                else:
                    entities.pop(deletion.id, None)
            for entity in update.entities:
                entities[entity.id] = entity
            areas.append([message.log_time, paint_area(entities)])
    out = {"schema": schema_name, "messages": count, "paint_area": areas, "entities": {}}
    out["paint_points"] = [
        [p.x, p.y, p.z]
        for id_, e in entities.items()
        if id_.startswith("paint-")
        for t in e.triangles
        for p in t.points
    ]
    for id_, e in entities.items():
        out["entities"][id_] = {
            "frame_id": e.frame_id,
            "triangles": sum(len(t.points) // 3 for t in e.triangles),
            "area": sum(triangle_area(t.points) for t in e.triangles),
            "loops": [[[p.x, p.y, p.z] for p in line.points] for line in e.lines],
            "cylinders": [
                {
                    "centre": [c.pose.position.x, c.pose.position.y, c.pose.position.z],
                    "orientation": [c.pose.orientation.w, c.pose.orientation.x, c.pose.orientation.y, c.pose.orientation.z],
                    "size": [c.size.x, c.size.y, c.size.z],
                }
                for c in e.cylinders
            ],
        }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
