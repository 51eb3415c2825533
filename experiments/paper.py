"""The paper's published numbers, printed beside ours and labelled as the paper's (reference only;
never mixed into ours)."""

PAPER_TABLE3 = {  # CMU Panoptic matching, by views: ARI, H, C, Vm
    2: (0.9875, 0.9968, 0.9925, 0.9943),
    3: (0.9977, 0.9993, 0.9981, 0.9986),
    5: (0.9941, 0.9978, 0.9937, 0.9956),
}
PAPER_TABLE4 = {2: (0.9770, 0.9966, 0.9886, 0.9923), 6: (0.9842, 0.9974, 0.9847, 0.9905)}  # ARP
PAPER_TABLE6 = {  # CMU Panoptic 3D: MPJPE mm, mAP, mR, t_pp ms, t_3Dg ms, t_3Di ms (GPU)
    "VoxelPose": (17.97, 96.61, 97.41, 135.92, 169.99, 50.53),
    "Triangulation": (22.63, 76.99, 85.10, 32.56, 10.06, 2.99),
    "Ours-detected": (26.06, 89.25, 92.63, 31.67, 19.65, 5.83),
    "Ours-projected": (17.84, 96.23, 97.76, 31.96, 19.94, 5.89),
    "Ours-average": (19.77, 95.67, 97.39, 32.22, 19.81, 5.85),
}
PAPER_TABLE7 = {  # ARP reprojection error, px, mean / median; cameras W0-W3 (walls), R0-R1 (robot)
    "M_1/6": (
        (14.65, 11.26),
        (11.84, 9.28),
        (14.02, 10.68),
        (12.18, 9.29),
        (6.69, 5.27),
        (9.05, 6.83),
    ),
    "M_2/6": (
        (14.35, 11.00),
        (12.02, 9.49),
        (14.04, 10.55),
        (12.36, 9.40),
        (7.06, 5.34),
        (7.79, 6.07),
    ),
    "M_6/6": ((10.28, 8.23), (8.28, 6.80), (11.12, 8.41), (7.88, 6.40), (8.98, 6.97), (9.49, 7.51)),
    "M_2/2": (
        (45.73, 26.85),
        (290.63, 15.62),
        (29.78, 21.86),
        (31.94, 19.24),
        (4.50, 3.37),
        (4.50, 3.38),
    ),
}
# The ARP Laboratory rig's robot cameras (the paper's R0, R1); the others are its walls.
ROBOT = ("orinbot_l", "orinbot_r")
