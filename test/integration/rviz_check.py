#!/usr/bin/env python3
"""Opens an rviz configuration (rviz's Python bindings), lets it run, prints every display's status, screenshots it.

Usage (under an X server, e.g. ``xvfb-run -a``; a ROS master must be running)::

    rviz_check.py CONFIG.rviz OUT.png [SECONDS]

Prints one line per display: ``DISPLAY <name> | <class> | <level> | <status texts>`` where level
is rviz's status (Ok, Warn, Error, or "none" when the display set no status), then
``SCREENSHOT <path>``. The screenshot is taken with ImageMagick's ``import -window root`` (the
whole virtual screen), or Qt's grab when ``import`` is missing. Exit code 0 when rviz came up.
"""
from __future__ import annotations

import shutil
import subprocess
import sys


def _status(display):
    """(level, [texts]) of a display's status child (rviz::StatusList, named "Status: <level>"), or ("none", [])."""
    for i in range(display.numChildren()):
        child = display.childAt(i)
        name = str(child.getName())
        if name.startswith("Status"):
            texts = []
            for j in range(child.numChildren()):
                s = child.childAt(j)
                texts.append(f"{s.getName()}: {s.getValue()}")
            level = name.split(":", 1)[1].strip() if ":" in name else str(child.getValue())
            return level, texts
    return "none", []


def main(argv) -> int:
    if len(argv) < 3:
        sys.stderr.write(__doc__)
        return 2
    config_path, out_png = argv[1], argv[2]
    seconds = float(argv[3]) if len(argv) > 3 else 12.0
    import rospy
    from python_qt_binding.QtCore import QTimer
    from python_qt_binding.QtWidgets import QApplication
    from rviz import bindings as rviz

    rospy.init_node("rviz_check", anonymous=True, disable_signals=True)
    app = QApplication(sys.argv[:1])
    frame = rviz.VisualizationFrame()
    frame.setSplashPath("")
    frame.initialize()
    reader = rviz.YamlConfigReader()
    config = rviz.Config()
    reader.readFile(config, config_path)
    if reader.error():
        sys.stdout.write(f"CONFIG_ERROR {reader.errorMessage()}\n")
        return 1
    frame.load(config)
    frame.resize(1400, 900)
    frame.show()

    def finish():
        root = frame.getManager().getRootDisplayGroup()
        for i in range(root.numDisplays()):
            d = root.getDisplayAt(i)
            level, texts = _status(d)
            sys.stdout.write(f"DISPLAY {d.getName()} | {d.getClassId()} | {level} | {'; '.join(texts)}\n")
        if shutil.which("import"):
            subprocess.run(["import", "-window", "root", out_png], check=False, timeout=30)
        else:
            frame.grab().save(out_png)
        sys.stdout.write(f"SCREENSHOT {out_png}\n")
        sys.stdout.flush()
        app.quit()

    QTimer.singleShot(int(seconds * 1000), finish)
    app.exec_()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
