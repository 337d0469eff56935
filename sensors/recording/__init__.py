"""Recording a real mission on a robot: the LMS capture, odometry, events and the clock mapping
(docs/recording.md)."""
