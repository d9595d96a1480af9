from glob import glob

from setuptools import find_packages, setup

package_name = "epi_vo"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        # the default parameter file, the RViz2 config and the Foxglove layout; the launch file
        ("share/" + package_name + "/config", sorted(glob("config/*.yaml") + glob("config/*.rviz")
                                                     + glob("config/*.json"))),
        ("share/" + package_name + "/launch", sorted(glob("launch/*.launch.py"))),
    ],
    install_requires=["setuptools", "numpy", "opencv-python-headless", "PyYAML", "rosbags", "mcap", "evo", "tqdm"],
    extras_require={"ba": ["gtsam"]},  # the windowed bundle adjustment (ba_window_keyframes > 0)
    zip_safe=True,
    maintainer="epi_vo developers",
    maintainer_email="dev@epi-vo.invalid",
    description="Monocular visual odometry with honest diagnostics",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "epi-vo = epi_vo.cli:main",
            "vo_node = epi_vo.ros.node:main",
            "vo_lifecycle_node = epi_vo.ros.lifecycle_node:main",
        ],
    },
)
