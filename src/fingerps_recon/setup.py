from glob import glob

from setuptools import find_packages, setup

package_name = "fingerps_recon"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml") + glob("config/*.xml")
         + glob("config/*.json") + glob("config/*.rviz")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="fingerps developers",
    maintainer_email="dev@fingerps.invalid",
    description=(
        "fingerps reconstruction: photometric stereo under a skin reflectance "
        "model, ridge enhancement, depth and point clouds; session recording to "
        "MCAP."
    ),
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            'recon_node = fingerps_recon.recon_node:main',
            'scan_node = fingerps_recon.scan_node:main',
            'offline_recon = fingerps_recon.offline.offline_recon:main',
            'recorder_node = fingerps_recon.recorder_node:main',
            'bag_recover = fingerps_recon.sessions.bag_recover:main',
            'bag_replay = fingerps_recon.bag_replay:main',
            'offline_tune = fingerps_recon.offline.offline_tune:main',
        ],
    },
)
