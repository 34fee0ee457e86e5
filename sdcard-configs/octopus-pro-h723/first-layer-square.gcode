; onechip sample: home, then one 40 mm first-layer square with a retract and
; a travel, around the bed centre. Temperatures are left to the user.
G28
G90
M82
G92 E0
G1 Z0.3 F600
G1 X97.5 Y97.5 F9000
G1 X137.5 Y97.5 E1.66 F1800
G1 X137.5 Y137.5 E3.33
G1 X97.5 Y137.5 E4.99
G1 X97.5 Y97.5 E6.65
G1 E5.85 F2100 ; retract
G1 Z1.3 F600
G1 X117.5 Y117.5 F9000
G1 Z0.3 F600
G1 E6.65 F2100 ; unretract
G1 X122.5 Y117.5 E6.86 F1200
G1 Z10 F600
M400
M114
