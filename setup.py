"""Build script of the lca_hil ROS 2 package (ament_python), also installable with pip."""

from pathlib import Path

from setuptools import find_packages, setup

PACKAGE = "lca_hil"
HERE = Path(__file__).parent


def _config_files(sub: str) -> list[str]:
    return sorted(str(p) for p in (HERE / "config" / sub).glob("*") if p.is_file())


setup(
    name=PACKAGE,
    version="0.1.0",
    description="HIL simulator for robot drive chains with irreversible gears (LCA robot)",
    long_description=(HERE / "README.md").read_text(encoding="utf-8"),
    long_description_content_type="text/markdown",
    license="Apache-2.0",
    python_requires=">=3.11",
    packages=[
        *find_packages(include=["lca_sim", "lca_sim.*", "lca_control", "lca_control.*"]),
        "lca_sim.data",
    ],
    # The shipped configs live in the top-level config/ folder (the ROS convention) and are also
    # package data of lca_sim.data, so a non-editable install finds them.
    package_dir={"lca_sim.data": "config"},
    package_data={
        "lca_sim.data": [
            "robots/*.yaml",
            "scenarios/*.yaml",
            "urdf/*.urdf",
            "ros/*.yaml",
            "can/*.yaml",
            "can/*.eds",
            "faults/*.yaml",
            "sweeps/*.yaml",
            "runs/*.yaml",
            "layouts/*",
            "ros2_control/*",
            "dds/*.xml",
        ]
    },
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + PACKAGE]),
        ("share/" + PACKAGE, ["package.xml"]),
        ("share/" + PACKAGE + "/config/robots", _config_files("robots")),
        ("share/" + PACKAGE + "/config/scenarios", _config_files("scenarios")),
        ("share/" + PACKAGE + "/config/urdf", _config_files("urdf")),
        ("share/" + PACKAGE + "/config/ros", _config_files("ros")),
        ("share/" + PACKAGE + "/config/can", _config_files("can")),
        ("share/" + PACKAGE + "/config/faults", _config_files("faults")),
        ("share/" + PACKAGE + "/config/sweeps", _config_files("sweeps")),
        ("share/" + PACKAGE + "/config/runs", _config_files("runs")),
        ("share/" + PACKAGE + "/config/layouts", _config_files("layouts")),
        ("share/" + PACKAGE + "/config/ros2_control", _config_files("ros2_control")),
        ("share/" + PACKAGE + "/config/dds", _config_files("dds")),
    ],
    install_requires=[
        "numpy>=1.26",
        "numba>=0.60",
        "pin>=3.0",
        "python-can>=4.3",
        "canopen>=2.3",
        # The cross-process CAN transport (lca_sim.canbus.remote) speaks its websocket protocol.
        "python-can-remote>=0.3,<0.4",
        "PyYAML>=6.0",
        "matplotlib>=3.8",
        # python-control: the Bode diagrams, margins and tuning of `lca-hil paper` / `tune`;
        # scipy: the identification's filters and confidence intervals.
        "control>=0.10",
        "scipy>=1.11",
        # `lca-hil sweep`: the points run on dask.distributed, the results are Parquet tables.
        "dask[distributed]>=2024.8",
        "pyarrow>=15",
        "setuptools<80",
    ],
    extras_require={
        # ROS 2 Jazzy from PyPI wheels: always through the ros-jazzy-* names.
        "ros": ["ros-jazzy-rclpy[fastrtps]", "ros-jazzy-common-interfaces", "rosbags>=0.10"],
        # Linters pinned: a new release must not turn a clean tree red on a fresh machine.
        "test": [
            "pytest>=8",
            "hypothesis>=6",
            "ruff==0.17.6",
            "mypy==2.4.1",
            "types-PyYAML",
            "colcon-common-extensions",
        ],
        "bench": ["mujoco>=3.1"],
    },
    entry_points={
        # The node scripts start in lca_sim.cli.nodes, which answers --help without ROS 2.
        "console_scripts": [
            "lca-sim = lca_sim.cli.sim:main",
            "lca-hil = lca_sim.cli.hil:main",
            "lca-simulator = lca_sim.cli.nodes:simulator",
            "lca-controller = lca_sim.cli.nodes:controller",
            "lca-record = lca_sim.cli.nodes:record",
            "lca-echo = lca_sim.cli.nodes:echo",
            "lca-plot = lca_sim.cli.bagplot:main",
            "lca-virtual-drive = lca_sim.cli.virtual_drive:main",
            "lca-can-bridge = lca_sim.cli.nodes:can_bridge",
            "lca-can-server = lca_sim.cli.can_server:main",
            # The names `ros2 run lca_hil <exe>` expects (installed to lib/lca_hil by colcon).
            "simulator = lca_sim.cli.nodes:simulator",
            "controller = lca_sim.cli.nodes:controller",
            "record = lca_sim.cli.nodes:record",
            "virtual_drive = lca_sim.cli.virtual_drive:main",
            "can_bridge = lca_sim.cli.nodes:can_bridge",
            "can_server = lca_sim.cli.can_server:main",
        ],
        # python-can interfaces: can.Bus(interface="lca_remote", channel="ws://127.0.0.1:54701/").
        "can.interface": ["lca_remote = lca_sim.canbus.remote:RemoteTransportBus"],
    },
    zip_safe=False,
)
