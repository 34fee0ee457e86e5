; onechip sample: heat up, home, then one 40 mm first-layer square with a
; retract and a travel, around the bed centre, with the part fan on.
M140 S60 ; bed heats while homing
M104 S200
G28
M190 S60
M109 S200
G90
M82
G92 E0
M106 S128
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
M107
M104 S0
M140 S0
M400
M105
M114
