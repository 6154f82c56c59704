"""Robot bridges: a physical robot (NAOqi, Furhat, ROS 2 through rosbridge) joins a station as any
robot client does and runs the study with its own voice and recogniser (docs/robots.md).

- :mod:`app.robots.robot`: what a bridge needs of a robot (say, listen, cues), one adapter per kind;
- :mod:`app.speech.vocabulary`: which words count as a yes or a no;
- :mod:`app.robots.bridge`: the loop that connects a robot to a station.
"""
