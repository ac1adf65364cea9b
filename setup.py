"""ament_python package set-up for asgp_ros (also installable with plain ``pip install .``)."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "asgp_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.rules")),
        (f"share/{PACKAGE}/launch", glob("launch/*.py")),
    ],
    python_requires=">=3.10",
    install_requires=[
        "setuptools",
        "numpy>=1.24",
        "scipy>=1.10",
        "opencv-python-headless>=4.8",
        "pyserial>=3.5",
        "rosbags>=0.10",
        "scikit-learn>=1.3",
        "threadpoolctl>=3.1",
        "matplotlib>=3.7",
        "PyYAML>=6",
    ],
    extras_require={
        # rclpy and the message packages come from the ros-jazzy-* wheels on PyPI, or from a
        # full ROS 2 Jazzy install (colcon), where pip must not try to replace them.
        "ros": ["ros-jazzy-rclpy[fastrtps]", "ros-jazzy-common-interfaces"],
        "test": ["pytest", "pytest-timeout", "pytest-xdist", "hypothesis", "GPy", "ruff",
                 "mypy", "colcon-common-extensions"],
    },
    zip_safe=True,
    maintainer="asgp_ros maintainers",
    maintainer_email="maintainers@asgp-ros.dev",
    description="Autoregressive sparse GP motion prediction for smart wheelchairs (ROS 2).",
    license="BSD-3-Clause",
    entry_points={
        "console_scripts": [
            "asgp = asgp_ros.cli:main",
            "predictor_node = asgp_ros.nodes.predictor_node:main",
            "vo_node = asgp_ros.nodes.vo_node:main",
            "serial_bridge_node = asgp_ros.nodes.serial_bridge_node:main",
            "shared_control_node = asgp_ros.nodes.shared_control_node:main",
        ],
    },
)
