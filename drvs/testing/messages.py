"""A ROS message through the wire format and back: what a subscriber would receive."""

import io


def round_trip(message):
    """``message`` serialized and deserialized into a new instance of its type (catches wrong
    field types, as rospy_message_converter's serialize_deserialize does)."""
    buffer = io.BytesIO()
    message.serialize(buffer)
    return type(message)().deserialize(buffer.getvalue())
