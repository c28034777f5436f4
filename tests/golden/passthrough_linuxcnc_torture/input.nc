%
(NCFIX F7 LINUXCNC XYZAC-TRT TCP, INVERSE TIME)
G21 G90 G17
M428 ;kinstype 0 = xyzac-trt (site remap)
G94 G0 X10 Y0 Z25 A0 C0
G93 G1 Z5 F60
G1  X  20.000  A -15.000  C -90.000  F 120
g1 x30 y5 a-30 c-30 f107.331
/N10 G1 x10.0 y 2.5 (block delete, lower case, spaced number)
N20 G0X +0. 12 34Y 7 ; LinuxCNC reads X0.1234 Y7
N30 G1 X007 Y.5 Z-0.000 F1200. (leading zeros, leading dot, negative zero)
N40 (MSG, active comment must survive) G1 X1
N56.78 G1 X2 ; fractional line number
o100 sub
g10 l20 p0 x-[#<_hal[xyzab_tdr_kins.x-rot-point]>+#<_hal[xyzab_tdr_kins.x-offset]>] y-#<_hal[x]>
o100 endsub
G94 G0 Z50	   
M429 ;identity kinematics (site remap)
M2
%
