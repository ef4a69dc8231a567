"""drvs.ros.markers: RViz markers of fields of view and detections (no master needed)."""

import doctest

import pytest
from visualization_msgs.msg import Marker

import drvs.ros.markers
from drvs.ros.markers import algorithm_colour, detection_markers, registry_markers
from drvs.testing.messages import round_trip


def test_doctest():
    assert doctest.testmod(drvs.ros.markers).failed == 0


def test_one_outline_and_one_name_per_registered_vision_system_after_a_delete_all():
    square = [(0, 0), (2, 0), (2, 1), (0, 1)]
    entries = [('/vs2/detect_object_boundary', square), ('/vs1/detect_object_boundary', square)]
    array = round_trip(registry_markers(entries))
    assert array.markers[0].action == Marker.DELETEALL
    outlines = [m for m in array.markers if m.ns == 'fields_of_view']
    names = [m for m in array.markers if m.ns == 'names']
    assert len(outlines) == 2 and len(names) == 2
    assert [m.text for m in names] == ['vs1', 'vs2']  # sorted: stable ids
    first = outlines[0]
    assert first.header.frame_id == 'map' and first.type == Marker.LINE_STRIP
    assert [(p.x, p.y) for p in first.points] == [(0, 0), (2, 0), (2, 1), (0, 1), (0, 0)]  # closed
    assert (names[0].pose.position.x, names[0].pose.position.y) == (1.0, 0.5)


def test_detections_are_coloured_by_algorithm_name_and_fade():
    outline = [(1, 1), (1.5, 1), (1.5, 1.5)]
    array = round_trip(
        detection_markers('/vs1/detect_object_boundary', 'colour:0,0,150,80,80,255', [outline] * 2)
    )
    assert [m.id for m in array.markers] == [0, 1]
    marker = array.markers[0]
    assert marker.ns == 'detections/vs1/detect_object_boundary/colour:0,0,150,80,80,255'
    assert marker.lifetime.to_sec() == 3.0
    expected = algorithm_colour('colour')  # by NAME: every colour model looks alike
    assert [marker.color.r, marker.color.g, marker.color.b] == pytest.approx(expected[:3], abs=1e-6)
    assert algorithm_colour('colour:1,2,3,4,5,6') != algorithm_colour('apriltag:tag36h11')
