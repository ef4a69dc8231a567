"""The site link's raw messages (drvs.ros.site_link.raw_message_class): published as the bytes
received, with the original's type, md5sum and definition, which a typed subscriber reads back."""

import io

from geometry_msgs.msg import PoseStamped
from std_msgs.msg import String

from drvs.ros.site_link import raw_message_class


def serialized(message) -> bytes:
    buffer = io.BytesIO()
    message.serialize(buffer)
    return buffer.getvalue()


def test_a_raw_message_is_the_bytes_it_came_in_with_the_original_type():
    Raw = raw_message_class(String._type, String._md5sum, String._full_text)
    assert (Raw._type, Raw._md5sum, Raw._full_text) == ('std_msgs/String', String._md5sum, String._full_text)
    raw = Raw()
    raw._buff = serialized(String('hello from site a'))
    assert String().deserialize(serialized(raw)).data == 'hello from site a'


def test_a_header_is_copied_as_it_came_not_renumbered():
    # rospy sets header.seq of a typed message with a header as it publishes it; a raw copy keeps it.
    assert PoseStamped._has_header
    Raw = raw_message_class(PoseStamped._type, PoseStamped._md5sum, PoseStamped._full_text)
    assert not Raw._has_header
    raw = Raw()
    original = PoseStamped()
    original.header.seq, original.header.frame_id, original.pose.position.x = 41, 'map', 2.5
    raw._buff = serialized(original)
    copied = PoseStamped().deserialize(serialized(raw))
    assert (copied.header.seq, copied.header.frame_id, copied.pose.position.x) == (41, 'map', 2.5)
