from glob import glob

from setuptools import find_packages, setup

package_name = "ptz_selfcal"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/launch", glob("launch/*.launch.py")),
        ("share/" + package_name + "/config", glob("config/*.yaml") + glob("config/*.xml")),
    ],
    package_data={package_name: ["config/*.yaml"]},
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="ptz_selfcal developers",
    maintainer_email="ptz_selfcal@example.com",
    description="Online self-calibration of a pan-tilt-zoom camera",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "ptz-selfcal = ptz_selfcal.tools.cli:main",
            # node executables for `ros2 run` / launch files on a full ROS install (each module has main())
            "frame_ingest = ptz_selfcal.nodes.frame_ingest:main",
            "homography_tracker = ptz_selfcal.nodes.homography_tracker:main",
            "calibrator = ptz_selfcal.nodes.calibrator:main",
            "mosaic = ptz_selfcal.nodes.mosaic_node:main",
        ],
    },
)
