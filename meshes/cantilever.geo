// Plane-stress cantilever for the Timoshenko-Goodier analytic solution.
// x in [0, L] (x = 0 free end with parabolic shear, x = L support), y in [-c, c].
// Parameters: h (element size), L, c.
DefineConstant[ h = 0.25, L = 8.0, c = 1.0 ];

Point(1) = {0, -c, 0, h};  Point(2) = {L, -c, 0, h};
Point(3) = {L,  c, 0, h};  Point(4) = {0,  c, 0, h};
Line(1) = {1, 2};  Line(2) = {2, 3};  Line(3) = {3, 4};  Line(4) = {4, 1};
Curve Loop(1) = {1, 2, 3, 4};
Plane Surface(1) = {1};

Physical Surface("beam") = {1};
Physical Curve("support") = {2};
Physical Curve("tip") = {4};
Physical Curve("top") = {3};
Physical Curve("bottom") = {1};
