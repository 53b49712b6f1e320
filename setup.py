"""ament_python package of ga_ros (also a plain pip-installable package)."""

from glob import glob

from setuptools import find_packages, setup

package_name = 'ga_ros'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
    ],
    # one entry per imported third-party package (pip names; package.xml names their rosdep
    # keys, test/package/test_packaging.py checks that both agree with requirements.txt)
    install_requires=['setuptools', 'numpy', 'scipy', 'cvxopt', 'opencv-python-headless',
                      'matplotlib', 'PyYAML', 'tqdm', 'rosbags', 'mcap', 'mcap-ros2-support',
                      'numba', 'threadpoolctl', 'lz4', 'zstandard'],
    extras_require={'metis': ['pymetis']},
    zip_safe=True,
    maintainer='ga_ros maintainers',
    maintainer_email='maintainers@ga-ros.invalid',
    description='Online track-by-track global alignment of sensor trajectories.',
    license='Apache-2.0',
    python_requires='>=3.11',
    entry_points={
        'console_scripts': [
            'ga-ros = ga_ros.cli.main:main',
            'alignment_node = ga_ros.ros.alignment_node:main',
            'lifecycle_alignment_node = ga_ros.ros.lifecycle_alignment_node:main',
            'vo_node = ga_ros.ros.vo_node:main',
            'map_node = ga_ros.ros.map_node:main',
        ],
    },
)
