package android.util;

public class AndroidException extends Exception {
    public AndroidException() {
        throw new RuntimeException("Stub!");
    }
}
