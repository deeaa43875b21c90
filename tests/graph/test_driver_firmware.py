"""driver_node with the LED board's AVR firmware under simavr as its board (``port:=`` the
simulator's pty): bursts through capture_burst and at a rate, every frame tagged with the
LED the firmware acknowledged (the folder camera shows the image of the LEDs the board
acknowledged when it grabs), and the camera trigger the driver set at connect pulsing after
every switch in the firmware's pin trace."""

from __future__ import annotations

import signal

import numpy as np
from board_trace import PERIOD_NS, stopped_trace
from led_images import led_folder, led_value

from fingerps_msgs.srv import CaptureBurst
from fingerps_ros import topics
from fingerps_ros.image_conversion import image_to_array

NS = "/" + topics.NAMESPACE
LEDS = list(range(7))


def test_driver_captures_bursts_through_the_firmware_and_sets_its_trigger(
        ros_node, start_node, spin_until, call_service, driver_topics, set_parameters,
        traced_firmware_board, tmp_path) -> None:
    sim = traced_firmware_board
    folder = led_folder(tmp_path / "images")
    driver = start_node("fingerps_driver", "driver_node", "--ros-args",
                        "-p", f"port:={sim.port}", "-p", "camera:=folder",
                        "-p", f"camera_folder:={folder}",
                        "-p", "trigger_delay_us:=100", "-p", "trigger_width_us:=50")
    driver.wait_in_graph(ros_node, "driver", NS)
    bursts, _, client = driver_topics
    spin_until(lambda: ros_node.count_publishers(f"{NS}/{topics.BURST}") >= 1,
               "the driver's burst publisher")

    def assert_truly_tagged(frames) -> None:
        assert [f.led_index for f in frames] == LEDS
        for frame in frames:
            image = image_to_array(frame.image)
            assert np.all(image == led_value(frame.led_index)), frame.led_index

    for _ in range(2):
        response = call_service(client, CaptureBurst.Request())
        assert response.success, response.message
        assert_truly_tagged(response.burst.frames)
    # the service's bursts are published too (reliable): count from after both are heard,
    # or a late one would stand in for a burst at the rate
    spin_until(lambda: len(bursts) >= 2, "the two captured bursts on the burst topic")

    published = len(bursts)
    assert all(result.successful for result in set_parameters("driver", {"rate": 5.0}))
    spin_until(lambda: len(bursts) >= published + 3, "three bursts at 5 a second",
               timeout=60.0)
    assert all(result.successful for result in set_parameters("driver", {"rate": 0.0}))
    for burst in bursts[published:published + 3]:
        assert_truly_tagged(burst.frames)

    driver.send_signal(signal.SIGINT)
    assert driver.wait() == 0
    trace = stopped_trace(sim)
    switches = trace.switches()[1:]  # after power-up
    lit = [t for t, mask in switches if mask]
    assert len(lit) >= 7 * (2 + 3)  # each LED of every burst, one at a time
    assert {mask for _, mask in switches} <= {0, *(1 << led for led in LEDS)}
    rises = trace.edges("trig", 1)
    # TRIG,100,50 at connect: 100 us -> 7 periods after every switch that lit an LED
    for start in lit:
        [rise] = [r for r in rises if start <= r < start + 1_000_000]
        assert 7 * PERIOD_NS <= rise - start < 8 * PERIOD_NS
