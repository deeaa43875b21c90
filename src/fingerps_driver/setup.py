from glob import glob

from setuptools import find_packages, setup

package_name = "fingerps_driver"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml")),
        ("share/" + package_name + "/launch", glob("launch/*.launch.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="fingerps developers",
    maintainer_email="dev@fingerps.invalid",
    description=(
        "fingerps driver: switches the LED board over serial, captures and tags "
        "bursts; the simulated rig and the board emulator."
    ),
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            'driver_node = fingerps_driver.driver_node:main',
            'board_emulator = fingerps_driver.board.board_emulator:main',
            'demo = fingerps_driver.demo:main',
            'bringup = fingerps_driver.bringup:main',
        ],
    },
)
