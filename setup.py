from glob import glob

from setuptools import find_packages, setup

package_name = 'lln_ros'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(include=[package_name, f'{package_name}.*']),
    package_data={package_name: ['weights/*.pt', 'weights/*.npz']},
    data_files=[
        ('share/ament_index/resource_index/packages', [f'resource/{package_name}']),
        (f'share/{package_name}', ['package.xml']),
        (f'share/{package_name}/config', glob('config/*.yaml') + glob('config/*.xml')),
        (f'share/{package_name}/rviz', glob('rviz/*.rviz')),
        (f'share/{package_name}/launch', glob('launch/*.py')),
    ],
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='lln_ros developers',
    maintainer_email='lln-ros@example.com',
    description='Online visual place recognition with discriminative landmarks (LLN, ICRA 2019)',
    license='Apache-2.0',
    extras_require={'test': ['pytest']},
    entry_points={
        'console_scripts': [
            'extractor = lln_ros.nodes.extractor:main',
            'matcher = lln_ros.nodes.matcher:main',
            'visualizer = lln_ros.nodes.visualizer:main',
            'lln-match = lln_ros.cli.match:main',
            'lln-bag = lln_ros.cli.bag:main',
            'lln-eval = lln_ros.cli.eval:main',
            'lln-train = lln_ros.cli.train:main',
            'lln-demo = lln_ros.cli.demo:main',
            'lln-reloc = lln_ros.cli.reloc:main',
            'lln-map = lln_ros.cli.map:main',
            'lln-export = lln_ros.cli.export:main',
        ],
    },
)
