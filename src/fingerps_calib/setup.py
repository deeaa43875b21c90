from glob import glob

from setuptools import find_packages, setup

package_name = "fingerps_calib"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="fingerps developers",
    maintainer_email="dev@fingerps.invalid",
    description=(
        "fingerps calibration: light directions from a shiny sphere, flat-field "
        "maps from a white target, camera intrinsics."
    ),
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            'calib_node = fingerps_calib.calib_node:main',
            'calibrate_lights = fingerps_calib.calibrate_lights_command:main',
            'calibrate_camera = fingerps_calib.calibrate_camera_command:main',
        ],
    },
)
